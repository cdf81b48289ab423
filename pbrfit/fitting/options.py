"""A fit's options: `FitOptions`, every option with its default, checked once when it is made
(the maps it frees and holds, `fit_arguments`; values, `check_options`; kinds, `check_kinds`;
named choices, `check_names`; the model, `check_model`), with messages worded for the Python API
or the command line (`OptionNames`)."""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, Callable, Mapping, Optional, Sequence, Union

import equinox as eqx
import jax
import numpy as np
import optimistix as optx

from ..lighting.pixel_ibl import PixelIBLSettings
from ..lighting.visibility import OCCLUSION_MODES, OcclusionSettings
from .defaults import COARSE_STEPS, CONTINUATION, IBL_MODES, LOSS_SCALE, MATERIAL_MAPS, QUALITY, STRUCTURED_ONLY
from ..physics.model import Model
from .noise import NOISE_LEVELS
from .parameters import FIT_GROUPS, prior
from .resolution import LEVEL_FACTOR
from .objective import LOSSES
from .solvers.names import DEFAULT_SOLVER, SOLVERS, is_structured, solver_for, solver_name
from .solvers.structured import CG_RTOL, NOISE_RTOL, StructuredLM
from .checkpoint import Checkpoint
from .stages.unconstrained import UNCONSTRAINED_SIGMA
from .uncertainty import MAX_UNCERTAINTY_RADIUS, WINDOW_RADIUS
from .observations import MAX_PIXEL_SAMPLES
from ..physics.textures import WRAPS

__all__ = ["FitOptions", "options_from", "OptionNames", "fit_arguments", "held_report", "check_options", "check_kinds", "check_names",
           "check_model", "check_normals", "occlusion_mode", "with_tolerances", "MATERIAL_MAPS", "IBL_MODES", "LOSS_SCALE", "FLOAT32_MAX",
           "MAX_MAP_SIDE", "MAX_SOLVER_STEPS"]

#: The largest finite float32, the solve's precision: the bound of every real-valued option.
FLOAT32_MAX = float(np.finfo(np.float32).max)
#: The largest map side an explicit ``resolution`` takes (the default stops at `pbrfit.fitting.resolution.MAX_RESOLUTION`).
MAX_MAP_SIDE = 8192
#: The most solver steps ``max_steps`` (and ``coarse_steps``) takes: far beyond any use, and within
#: the int32 step counters of the jitted loops.
MAX_SOLVER_STEPS = 1_000_000


def _integer(x) -> bool:
    """An integer option's value: a Python or numpy integer, not a bool."""
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def _real(x) -> bool:
    """A real-valued option's value: a Python or numpy integer or float, not a bool (``smooth=True``
    is no weight) and not complex."""
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))


@dataclasses.dataclass(frozen=True)
class OptionNames:
    """How `fit_arguments` and `check_options` name what they refuse: by the Python keyword
    (default: ``smooth``, ``solver='lm'``, ``fixed``) or, with ``flags``, by the command line's
    flag (``--smooth``, ``--solver lm``); ``held_by`` then gives the flag that holds each map
    (``--roughness`` or ``--roughness-from``)."""

    flags: bool = False
    held_by: Mapping[str, str] = dataclasses.field(default_factory=dict)

    def option(self, name: str) -> str:
        return "--" + name.replace("_", "-") if self.flags else name

    def setting(self, name: str, value) -> str:
        return f"{self.option(name)} {value}" if self.flags else f"{name}={value!r}"

    def holder(self, name: str) -> str:
        """Who holds map ``name``: its flag, or the ``fixed`` argument."""
        return self.held_by.get(name, self.option(name)) if self.flags else "fixed"

    def held_value(self, name: str) -> str:
        return self.holder(name) if self.flags else f"fixed[{name!r}]"


def fit_arguments(fit=None, fixed: Optional[Mapping] = None,
                  names: OptionNames = OptionNames()) -> tuple[tuple[str, ...], dict]:
    """The maps a fit frees and the values it holds, checked (`ValueError` otherwise, worded
    with ``names``).

    ``fit``: names from `FIT_GROUPS` (a sequence, or one string of comma-separated names); None
    (default): every map of `MATERIAL_MAPS` that ``fixed`` does not hold. ``fixed``: {map: value}
    for maps of `MATERIAL_MAPS`, finite and in [0, 1]: base colour as one grey value, R, G, B or an
    (H, W, 3) map; metallic and roughness as one value or an (H, W) or (H, W, 1) map (any size:
    resampled to the fit's by `pbrfit.physics.textures.resample_map`). A map may not be both fitted and
    held, and something must be fitted.
    Returns (fit, fixed) with the held values as float32 arrays of shape (), (3,), (H, W, C)."""
    held = {}
    for name, value in dict(fixed or {}).items():
        if name not in MATERIAL_MAPS:
            raise ValueError(f"fixed: unknown map {name!r}; expected some of {', '.join(MATERIAL_MAPS)}"
                             + (" (a normal map can only be fitted)" if name == "normal" else ""))
        label = names.held_value(name)
        try:
            v = np.asarray(value)
            if v.dtype.kind not in "biuf":
                raise TypeError
            v = v.astype(np.float32)
        except (TypeError, ValueError):
            raise ValueError(f"{label}: expected numbers, got {value!r}") from None
        channels = len(FIT_GROUPS[name])
        if name != "base_color" and v.ndim == 2:
            v = v[..., None]
        ok = v.ndim == 0 or (v.ndim == 1 and v.shape[0] in (1, channels)) or (
            v.ndim == 3 and v.shape[-1] == channels and min(v.shape[:2]) >= 1)
        if not ok:
            want = "a value, R, G, B or an (H, W, 3) map" if channels == 3 else "a value or an (H, W) map"
            raise ValueError(f"{label}: expected {want}, got shape {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{label}: holds NaN or inf")
        if np.any(v < 0.0) or np.any(v > 1.0):
            found = f"got {v.item():g}" if v.size == 1 else f"found {v.min():g} to {v.max():g}"
            raise ValueError(f"{label}: expected values in [0, 1], {found}")
        held[name] = v.reshape(-1)[0] if v.ndim == 1 and v.shape[0] == 1 else v
    option = names.option("fit")
    if fit is None:
        fit = tuple(name for name in MATERIAL_MAPS if name not in held)
    else:
        listed = fit.split(",") if isinstance(fit, str) else list(fit)
        fit = tuple(str(name).strip() for name in listed if str(name).strip())
        for name in fit:
            if name not in FIT_GROUPS:
                raise ValueError(f"{option}: unknown map {name!r}; expected some of {', '.join(FIT_GROUPS)}")
            if fit.count(name) > 1:
                raise ValueError(f"{option}: lists {name} twice")
            if name in held:
                raise ValueError(f"{option}: lists {name}, which {names.holder(name)} holds too; drop one of the two")
    if not fit:
        why = "every map is held fixed" if held and len(held) == len(MATERIAL_MAPS) else "it names no map"
        raise ValueError(f"{option}: nothing to fit ({why})")
    return fit, held


def check_options(options: "FitOptions") -> None:
    """`ValueError` (worded with ``options.names``) for option values out of range, or given to a
    mode that does not read them: `fit`, `pbrfit.fitting.api.fit_observations` and the command
    line refuse alike. ``solver`` is a name of `SOLVERS` or an optimistix solver; ``rtol``,
    ``atol``, ``cg_rtol`` and ``noise_rtol`` None stand for the solver's own (a `StructuredLM`'s are
    checked as if given)."""
    (resolution, maps, solver, max_steps, coarse_steps, rtol, atol, cg_rtol, noise_rtol, loss_scale, smooth,
     coarse_to_fine, continuation, uncertainty_radius, unconstrained_sigma) = (
        getattr(options, name) for name in _CHECKED)
    names = options.names
    say = names.option
    if not _solver_object(solver) and (not isinstance(solver, str) or solver not in SOLVERS):
        raise ValueError(f"{say('solver')}: must be one of {', '.join(SOLVERS)}, or an optimistix least-squares "
                         f"solver or minimiser, got {solver!r}")
    if isinstance(solver, StructuredLM):  # its own tolerances, where the options do not set them
        rtol, atol = (solver.rtol if rtol is None else rtol), (solver.atol if atol is None else atol)
        if cg_rtol is None and _real(solver.cg_rtol):  # (an array: a runner's, not checked)
            cg_rtol = solver.cg_rtol
        noise_rtol = solver.noise_rtol if noise_rtol is None else noise_rtol
    if maps not in ("texture", "none"):
        raise ValueError(f"{say('maps')}: must be 'texture' or 'none', got {maps!r}")
    if resolution is not None:
        sides = [resolution] if np.ndim(resolution) == 0 else list(np.ravel(resolution))
        if (np.ndim(resolution) != 0 and len(sides) != 2) or any(
                not _integer(r) or not 1 <= r <= MAX_MAP_SIDE for r in sides):
            want = "an integer" if names.flags else "an integer N or a pair (H, W) of integers"
            raise ValueError(f"{say('resolution')}: must be {want} from 1 to {MAX_MAP_SIDE}, got {resolution!r}")
    for name, value, least in (("max_steps", max_steps, 1), ("coarse_steps", coarse_steps, 0),
                               ("uncertainty_radius", uncertainty_radius, 0)):
        most = MAX_UNCERTAINTY_RADIUS if name == "uncertainty_radius" else MAX_SOLVER_STEPS
        if value is None and name == "max_steps":  # the solver's own default
            continue
        if not _integer(value) or not least <= value <= most:
            raise ValueError(f"{say(name)}: must be an integer from {least} to {most}, got {value!r}")
    for name, value in (("rtol", rtol), ("atol", atol), ("noise_rtol", noise_rtol), ("smooth", smooth)):
        if value is None and name != "smooth":  # the solver's own
            continue
        if not (_real(value) and math.isfinite(value) and value >= 0):
            raise ValueError(f"{say(name)}: must be a finite number >= 0, got {value!r}")
        if value > FLOAT32_MAX:  # the solve runs in float32
            raise ValueError(f"{say(name)}: must be at most {FLOAT32_MAX:.3g} (float32), got {value!r}")
    weights = () if continuation is None else np.ravel(np.asarray(continuation, dtype=object))
    if not all(_real(w) and math.isfinite(w) and 0 <= w <= FLOAT32_MAX for w in weights):
        raise ValueError(f"{say('continuation')}: expected weights >= 0 within float32, got {continuation!r}")
    if not (_real(loss_scale) and math.isfinite(loss_scale) and loss_scale > 0):
        raise ValueError(f"{say('loss_scale')}: must be a finite number > 0, got {loss_scale!r}")
    if not (_real(unconstrained_sigma) and unconstrained_sigma > 0):  # (inf: hold none)
        raise ValueError(f"{say('unconstrained_sigma')}: must be a number > 0 (inf: hold no texel), "
                         f"got {unconstrained_sigma!r}")
    if cg_rtol is not None and not (_real(cg_rtol) and 0.0 < cg_rtol < 1.0):
        raise ValueError(f"{say('cg_rtol')}: must be a number in (0, 1), got {cg_rtol!r}")
    given_continuation = continuation is not None and len(np.ravel(continuation)) > 0 \
        and tuple(np.ravel(continuation)) != CONTINUATION
    if not is_structured(solver):  # options only the structured solver reads
        for name, given in (("cg_rtol", cg_rtol is not None and cg_rtol != CG_RTOL),
                            ("noise_rtol", noise_rtol is not None and noise_rtol != NOISE_RTOL),
                            ("continuation", given_continuation)):
            if given:
                raise ValueError(f"{say(name)}: only the {DEFAULT_SOLVER} solver uses it, "
                                 f"not {names.setting('solver', solver_name(solver))}")
    if maps == "none":  # one texel: no map size, no neighbours, no levels
        for name, given in (("resolution", resolution is not None), ("smooth", smooth > 0),
                            ("continuation", given_continuation), ("coarse_to_fine", coarse_to_fine)):
            if given:
                raise ValueError(f"{say(name)}: {names.setting('maps', 'none')} fits one uniform material (1 x 1 maps)")


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Every option of a fit, with its default (`pbrfit.fit` documents each), checked once when
    made: a value out of range, of the wrong kind or given to a mode that does not read it raises
    `ValueError` in one line, worded by ``names`` (the Python keyword, or the command line's flag).

    ``FitOptions(resolution=64, fixed={"metallic": 0.0})``; ``dataclasses.replace(options, ...)``
    (or ``pbrfit.fit(capture, options, **overrides)``) makes a checked copy. ``fit`` and ``fixed``
    stay as given; `fitted` and `held` are what they mean (`fit_arguments`): the maps freed, as a
    tuple, and the values held, as float32 arrays.
    """

    # what is fitted, at what size
    resolution: Union[None, int, tuple[int, int]] = None
    fit: Optional[Sequence[str]] = None
    fixed: Optional[Mapping[str, Any]] = None
    maps: str = "texture"
    model: Union[None, Model, Mapping[str, Any]] = None
    # the solver and when it stops: an optimistix solver, or its name in `SOLVERS` (made by
    # `solver_for`); rtol, atol, cg_rtol and noise_rtol, when given, set the solver's (None: its own)
    solver: Any = dataclasses.field(default_factory=StructuredLM)
    max_steps: Optional[int] = None
    coarse_steps: int = COARSE_STEPS
    rtol: Optional[float] = None
    atol: Optional[float] = None
    cg_rtol: Optional[float] = None
    noise_rtol: Optional[float] = None
    # the objective
    loss: str = "l2"
    loss_scale: float = LOSS_SCALE
    smooth: float = 0.0
    noise_level: str = "uniform"
    # the schedule
    coarse_to_fine: bool = False
    level_factor: int = LEVEL_FACTOR
    init: str = "grid"
    search: bool = True
    continuation: Optional[Sequence[float]] = CONTINUATION
    # the stages after the solve
    repair: bool = True
    uniform_check: bool = True
    unconstrained_sigma: float = UNCONSTRAINED_SIGMA
    uncertainty_radius: int = WINDOW_RADIUS
    # how the images are modelled
    ibl: str = IBL_MODES[0]
    pixel_ibl_settings: PixelIBLSettings = PixelIBLSettings()
    occlusion: Optional[str] = None  # None: by the light model (`occlusion_mode`)
    occlusion_settings: OcclusionSettings = OcclusionSettings()
    pixel_samples: Union[str, int] = "auto"
    wrap: str = "repeat"
    # where it runs
    devices: Optional[Sequence[Any]] = None
    background_compile: bool = True
    cache_dir: Any = None
    progress: Optional[Callable[[dict], Any]] = None
    checkpoint: Any = None
    # the speed ladder: a rung of `QUALITY`, whose settings fill the options not given
    quality: str = "default"
    #: how refusals name the options (not an option: left out of comparisons)
    names: OptionNames = dataclasses.field(default=OptionNames(), compare=False, repr=False)

    def __post_init__(self):
        say = self.names.option
        if self.quality not in QUALITY:
            raise ValueError(f"{say('quality')} must be one of {', '.join(QUALITY)}, got {self.quality!r}")
        if self.ibl not in IBL_MODES:
            raise ValueError(f"{say('ibl')} must be one of {', '.join(IBL_MODES)}, got {self.ibl!r}")
        fit, fixed = fit_arguments(self.fit, self.fixed, self.names)
        object.__setattr__(self, "_fitted", fit)
        object.__setattr__(self, "_held", fixed)
        check_options(self)
        solver = with_tolerances(self.solver, self.rtol, self.atol, self.cg_rtol, self.noise_rtol)
        object.__setattr__(self, "solver", solver)
        check_kinds(**{name: getattr(self, name) for name in _KINDS})
        check_names(noise_level=self.noise_level, loss=self.loss, init=self.init, wrap=self.wrap,
                    pixel_samples=self.pixel_samples)
        check_normals(self.ibl, fit, self.names)
        if not isinstance(self.pixel_ibl_settings, PixelIBLSettings):
            raise ValueError(f"pixel_ibl_settings: expected a PixelIBLSettings, got {self.pixel_ibl_settings!r}")
        if self.occlusion is not None and self.occlusion not in OCCLUSION_MODES:
            raise ValueError(f"{say('occlusion')} must be one of {', '.join(OCCLUSION_MODES)}, got {self.occlusion!r}")
        if self.checkpoint is not None and not isinstance(self.checkpoint, Checkpoint):
            raise ValueError(f"checkpoint: expected a pbrfit.fitting.checkpoint.Checkpoint or None, got {self.checkpoint!r}")
        if not isinstance(self.occlusion_settings, OcclusionSettings):
            raise ValueError(f"occlusion_settings: expected an OcclusionSettings, got {self.occlusion_settings!r}")
        if isinstance(self.model, Mapping):  # fields of the capture's own model to change
            try:
                Model(**self.model)
            except (TypeError, ValueError) as err:
                raise ValueError(f"{say('model')}: {err}") from None
            if self.model.get("metallic") is False and "metallic" in fit:
                raise ValueError(f"{say('model')}: metallic=False has no metal lobe, and metallic is fitted "
                                 f"(hold it with {self.names.holder('metallic')})")
        elif self.model is not None:
            check_model(self.model, fit)
            check_normals(self.model.ibl, fit, self.names)
            if self.model.ibl == "monte_carlo":
                raise ValueError("model: Model(ibl='monte_carlo') is the reference integrator, not a fit's "
                                 "shading; use 'split_sum' or 'per_pixel'")

    @property
    def fitted(self) -> tuple[str, ...]:
        """The maps the fit frees (``fit``, or every material map ``fixed`` does not hold)."""
        return self._fitted

    @property
    def held(self) -> dict:
        """The values ``fixed`` holds, as float32 arrays."""
        return self._held

    def replace(self, **overrides) -> "FitOptions":
        """A checked copy with ``overrides``."""
        return dataclasses.replace(self, **overrides) if overrides else self


#: The options `check_options` checks, and those `check_kinds` checks.
_CHECKED = ("resolution", "maps", "solver", "max_steps", "coarse_steps", "rtol", "atol", "cg_rtol", "noise_rtol",
            "loss_scale", "smooth", "coarse_to_fine", "continuation", "uncertainty_radius", "unconstrained_sigma")
_KINDS = ("coarse_to_fine", "search", "background_compile", "uniform_check", "repair", "progress", "level_factor",
          "devices")


def _solver_object(solver) -> bool:
    """Whether ``solver`` is a solver object a fit can run (an optimistix least-squares solver
    or minimiser)."""
    return isinstance(solver, (optx.AbstractLeastSquaresSolver, optx.AbstractMinimiser))


def with_tolerances(solver, rtol=None, atol=None, cg_rtol=None, noise_rtol=None):
    """The solver object of ``solver`` (a name of `SOLVERS`, made by `solver_for`, or an object)
    with the tolerances given set (None: its own; ``cg_rtol`` and ``noise_rtol`` are the structured
    solver's alone)."""
    if isinstance(solver, str):
        return solver_for(solver, rtol, atol, cg_rtol, noise_rtol)
    for name, value in (("rtol", rtol), ("atol", atol), ("cg_rtol", cg_rtol), ("noise_rtol", noise_rtol)):
        if value is not None and (name in ("rtol", "atol") or isinstance(solver, StructuredLM)):
            solver = eqx.tree_at(lambda s: getattr(s, name), solver, float(value))
    return solver


def _with_quality(generated_init):
    """`FitOptions`' ``__init__``: ``quality``'s rung of `QUALITY` sets the options it names that
    are not given (those only the structured solver reads, where it runs); then the dataclass's
    own ``__init__``. `dataclasses.replace` gives every field, so a copy keeps its values."""

    @functools.wraps(generated_init)
    def __init__(self, **options):
        structured = is_structured(options.get("solver", DEFAULT_SOLVER))
        for name, value in QUALITY.get(options.get("quality", "default"), {}).items():
            if name not in options and (structured or name not in STRUCTURED_ONLY):
                options[name] = value
        generated_init(self, **options)

    return __init__


FitOptions.__init__ = _with_quality(FitOptions.__init__)


def options_from(options: Optional[FitOptions], overrides: Mapping[str, Any]) -> FitOptions:
    """``options`` (default `FitOptions()`) with ``overrides``, checked; an unknown keyword is a
    `TypeError` naming it, as a function's would be."""
    fields = {f.name for f in dataclasses.fields(FitOptions)}
    unknown = [name for name in overrides if name not in fields]
    if unknown:
        raise TypeError(f"unknown fit option {unknown[0]!r} (FitOptions has {', '.join(sorted(fields - {'names'}))})")
    if options is None:
        return FitOptions(**overrides)
    if not isinstance(options, FitOptions):
        raise TypeError(f"options: expected a pbrfit.FitOptions, got {type(options).__name__}")
    return options.replace(**overrides)


def held_report(fit: Sequence[str], fixed: Optional[Mapping]) -> dict:
    """What each material map not fitted was held at, for the report: ``{"source": "value",
    "value": v}`` (a number, or R, G, B), ``{"source": "map", "shape": [H, W], "mean": m}`` or,
    for a map neither fitted nor given, ``{"source": "prior", "value": v}`` (`PRIOR`)."""
    out = {}
    for name in ("base_color", "metallic", "roughness"):
        if name in fit:
            continue
        chans = list(FIT_GROUPS[name])
        value = None if fixed is None else fixed.get(name)
        if value is None:
            v = [float(c) for c in prior(5)[chans]]
            out[name] = dict(source="prior", value=v if len(v) > 1 else v[0])
        elif np.ndim(value) == 3:
            a = np.asarray(value, np.float64)
            mean = [float(c) for c in a.reshape(-1, a.shape[-1]).mean(0)]
            out[name] = dict(source="map", shape=list(a.shape[:2]), mean=mean if len(mean) > 1 else mean[0])
        else:
            v = [float(c) for c in np.ravel(value)]
            out[name] = dict(source="value", value=v if len(v) > 1 else v[0])
    return out


def occlusion_mode(occlusion: Optional[str], ibl: Optional[str]) -> str:
    """The occlusion a fit models (``occlusion``: the option; ``ibl``: the model's light model):
    as asked, else by the light model: "auto" with per-pixel integrals, the physical model, for
    captures from a path tracer, a camera or pbrfit's Monte Carlo reference, whose light the mesh
    shadows; "off" with the split sum, the model of pbrfit's own split-sum renders, which cast
    no shadows of the environment."""
    if occlusion is not None:
        return occlusion
    return "auto" if ibl == "per_pixel" else "off"


def check_normals(ibl: Optional[str], fit: Sequence[str], names: OptionNames = OptionNames()) -> None:
    """`ValueError` where normals are fitted under per-pixel IBL (``ibl``: the option's or the
    model's): the per-pixel integrals hold each pixel's normal fixed."""
    if ibl == "per_pixel" and "normal" in fit:
        raise ValueError(f"{names.setting('ibl', 'per_pixel')}: fitted normals need "
                         f"{names.setting('ibl', 'split_sum')} (per-pixel integrals hold the normals fixed)")


def check_kinds(*, progress, level_factor, devices, **switches) -> None:
    """`ValueError` for arguments of the wrong kind, before any work: a switch that is not a
    bool (``search="no"`` read as true), a ``progress`` that cannot be called (it failed inside
    the compiled solve), a ``level_factor`` below 2, ``devices`` that are not JAX devices."""
    for name, value in switches.items():
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"{name}: expected True or False, got {value!r}")
    if progress is not None and not callable(progress):
        raise ValueError(f"progress: expected a function of one dict, or None, got {progress!r}")
    if not _integer(level_factor) or level_factor < 2:
        raise ValueError(f"level_factor: expected an integer >= 2, got {level_factor!r}")
    if devices is not None:
        try:
            listed = [devices] if isinstance(devices, (str, bytes, jax.Device)) else list(devices)
        except TypeError:
            listed = [devices]
        if isinstance(devices, (str, bytes, jax.Device)) or not listed \
                or not all(isinstance(d, jax.Device) for d in listed):
            raise ValueError(f"devices: expected a sequence of JAX devices (jax.devices()), got {devices!r}")


def check_names(*, noise_level, loss, init, wrap, pixel_samples="auto") -> None:
    """`ValueError` for a named choice out of its list (`pbrfit.fitting.api.fit_observations`; `pbrfit.fit` before
    it reads the capture and casts its rays, with ``pixel_samples`` too)."""

    for name, value, choices in (("noise_level", noise_level, NOISE_LEVELS), ("loss", loss, LOSSES),
                                 ("init", init, ("grid", "prior")), ("wrap", wrap, WRAPS)):
        if not isinstance(value, str) or value not in choices:
            raise ValueError(f"{name} must be one of {', '.join(choices)}, got {value!r}")
    if pixel_samples != "auto" and not (_integer(pixel_samples) and 1 <= pixel_samples <= MAX_PIXEL_SAMPLES):
        raise ValueError(f"pixel_samples must be 'auto' or an integer from 1 to {MAX_PIXEL_SAMPLES}, "
                         f"got {pixel_samples!r}")


def check_model(model, fit: Sequence[str]) -> None:
    """`ValueError` for a ``model`` that is not a `Model`, or that has no metal lobe while
    metallic is fitted."""
    if not isinstance(model, Model):
        raise ValueError(f"model: expected a pbrfit.Model, got {model!r}")
    if "metallic" in fit and not model.metallic:
        raise ValueError("fit: metallic is fitted, and the model has no metal lobe (Model(metallic=False)): "
                         "the images could not say anything about it")
