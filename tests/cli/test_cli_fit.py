"""`pbrfit fit`: the output folder of the capture spec, and options that end with status 2."""

import json

import numpy as np
import pytest

from pbrfit import FitOptions
from pbrfit.cli.main import main
from pbrfit.fitting.defaults import NOISE_RTOL
from pbrfit.io.images import read_image

SPEC_FILES = (
    "base_color.exr", "base_color.png", "metallic.exr", "roughness.exr", "metallic_roughness.png",
    "uncertainty.exr", "coverage.exr", "material.glb", "report.json",
)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("fitcli")
    cap = root / "cap"
    assert main(["synth", "peer-plane", "--out", str(cap), "--size", "32", "--views", "3", "--texture-size", "8",
                 "--quiet"]) == 0
    return cap


def test_fit_writes_the_spec_output(capture, tmp_path, monkeypatch):
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "out"
    assert main(["fit", str(capture), "--out", str(out), "--resolution", "8", "--max-steps", "8", "--quiet"]) == 0
    for name in SPEC_FILES:
        assert (out / name).is_file(), name
    assert not (out / "normal.png").exists()  # normals were not fitted
    unc, info = read_image(out / "uncertainty.exr")
    assert unc.shape == (8, 8, 5) and info.channel_names == ("R", "G", "B", "metallic", "roughness")
    cov, _ = read_image(out / "coverage.exr")
    assert cov.shape == (8, 8, 1) and cov.max() > 0
    # unseen texels have infinite uncertainty, seen ones finite
    seen = cov[..., 0] > 0
    assert np.all(np.isfinite(unc[seen])) and np.all(np.isinf(unc[~seen]))
    report = json.loads((out / "report.json").read_text())
    for key in ("model", "solver", "steps", "times", "final_loss", "psnr", "devices", "truth_rmse", "wall_time"):
        assert key in report, key
    assert report["iterations"] == report["steps"] > 0  # the capture spec's word
    assert len(report["psnr"]) == 3
    assert set(report["truth_rmse"]) == {"base_color", "metallic", "roughness"}
    # a noiseless capture of the fit's own model: fitted exactly (measured: RMSE 1e-8 to 8e-8, PSNR 156 dB)
    assert max(report["truth_rmse"].values()) < 1e-4 and min(report["psnr"]) > 80.0, report
    # linear images rendered at pixel centres: the footprint test finds no box's blur, and the
    # centres' fit is kept without fitting the samples
    foot = report["footprint"]
    assert foot["selected"] == 1 and report["pixel_samples"] == 1 and "energies" not in foot, foot
    assert abs(foot["evidence"]["slope"]) < 0.1 and "footprint_probe" not in report["times"]
    assert len(list((out / "views").glob("*.png"))) == 3
    plot, _ = read_image(out / "convergence.png")
    assert plot.shape == (320, 520, 3) and plot.min() < 0.5 < plot.max()  # drawn, not blank
    # deterministic: the same command again writes the same bytes, and the same report but its times
    again = tmp_path / "again"
    assert main(["fit", str(capture), "--out", str(again), "--resolution", "8", "--max-steps", "8", "--quiet"]) == 0
    for name in ("base_color.exr", "metallic.exr", "roughness.exr", "uncertainty.exr", "coverage.exr", "material.glb"):
        assert (again / name).read_bytes() == (out / name).read_bytes(), name
    timings = ("wall_time", "times", "stages")
    other = json.loads((again / "report.json").read_text())
    assert {k: v for k, v in other.items() if k not in timings} == {k: v for k, v in report.items() if k not in timings}
    assert [{k: v for k, v in s.items() if k != "seconds"} for s in other["stages"]] == [
        {k: v for k, v in s.items() if k != "seconds"} for s in report["stages"]]


def test_fit_with_an_estimated_noise_level(capture, tmp_path, monkeypatch, capsys):
    """Two fits, the second weighted by the first's noise level: report.json says so, the summary
    line too. On sRGB images the first fit chooses the pixel footprint, and the second keeps it."""
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    noisy = tmp_path / "noisy"
    assert main(["synth", "peer-plane", "--out", str(noisy), "--size", "32", "--views", "3", "--texture-size", "8",
                 "--noise", "0.02", "--noise-model", "relative", "--format", "png16", "--quiet"]) == 0
    out = tmp_path / "out"
    assert main(["fit", str(noisy), "--out", str(out), "--resolution", "8", "--max-steps", "8",
                 "--noise-level", "estimated", "--no-search", "--no-repair", "--no-uniform-check"]) == 0
    report = json.loads((out / "report.json").read_text())
    level = report["noise_level"]
    assert level["mode"] == "estimated" and len(level["sigma"]) == len(level["values"]) >= 1
    assert report["steps"] > level["first_fit"]["steps"] > 0
    assert report["footprint"]["selected"] in (1, 2) and report["pixel_samples"] == report["footprint"]["selected"]
    lines = capsys.readouterr().out.strip().splitlines()  # one summary line (no progress bar off a terminal)
    assert len(lines) == 1 and "weighted by the estimated noise level" in lines[0], lines
    assert lines[0].endswith(f"; wrote {out}")
    # both fits' times, and the rest as "other", add up to the wall time
    assert sum(v for k, v in report["times"].items() if k != "compile_background") == pytest.approx(report["wall_time"])
    assert max(report["truth_rmse"].values()) < 0.1, report["truth_rmse"]


def test_noise_level_option_reaches_the_fit():
    from pbrfit.cli.main import build_parser
    from pbrfit.cli.fit import fit_options

    def options(*extra):
        return fit_options(build_parser().parse_args(["fit", "CAP", "--out", "OUT", *extra]))

    assert options().noise_level == "uniform" and options("--noise-level", "estimated").noise_level == "estimated"


def test_fit_with_normals_writes_normal_png(capture, tmp_path, monkeypatch):
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "out"
    assert main(["fit", str(capture), "--out", str(out), "--resolution", "8", "--max-steps", "4",
                 "--fit", "base_color,roughness,normal", "--metallic", "0", "--no-search", "--no-repair",
                 "--no-uniform-check", "--quiet"]) == 0
    normal, _ = read_image(out / "normal.png")
    assert normal.shape == (8, 8, 3)
    n = normal * 2.0 - 1.0  # tangent space, n * 0.5 + 0.5 in 8 bits
    # unit vectors to 8-bit rounding, near +Z on this flat plane (measured: 0.0036 off unit, z >= 0.992)
    assert np.abs(np.linalg.norm(n, axis=-1) - 1.0).max() < 0.01 and n[..., 2].min() > 0.95
    unc, info = read_image(out / "uncertainty.exr")
    assert unc.shape == (8, 8, 5)  # the spec's five channels; the normal's σ is in the report
    report = json.loads((out / "report.json").read_text())
    assert report["fitted"][-2:] == ["normal_sx", "normal_sy"] and "normal_slope_sigma_median" in report


def test_uniform_fit_writes_one_texel_maps(capture, tmp_path, monkeypatch):
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "out"
    assert main(["fit", str(capture), "--out", str(out), "--maps", "none", "--roughness", "0.5", "--quiet"]) == 0
    base, _ = read_image(out / "base_color.exr")
    rough, _ = read_image(out / "roughness.exr")
    assert base.shape[:2] == (1, 1) and float(rough[0, 0, 0]) == pytest.approx(0.5)
    unc, _ = read_image(out / "uncertainty.exr")
    assert float(unc[0, 0, 4]) == 0.0  # held fixed
    report = json.loads((out / "report.json").read_text())  # the spec: report.json holds the five numbers
    np.testing.assert_allclose(report["material"]["base_color"], base[0, 0], rtol=1e-6)
    assert report["material"]["roughness"] == pytest.approx(0.5) and report["material_sigma"]["roughness"] == 0.0
    assert 0.0 <= report["material"]["metallic"] <= 1.0 and report["material_sigma"]["base_color"][0] > 0.0
    assert report["held"] == {"roughness": {"source": "value", "value": 0.5}}
    # a second fit to the same folder replaces the first, files the first wrote and this one does
    # not included (as the marker lists them), but not a file someone saved into it since
    marker = out / ".pbrfit-output"
    (out / "stale.txt").write_text("from the first fit")
    assert main(["fit", str(capture), "--out", str(out), "--maps", "none", "--quiet"]) == 2
    assert (out / "stale.txt").is_file()
    marker.write_text(marker.read_text() + "stale.txt\n")
    assert main(["fit", str(capture), "--out", str(out), "--maps", "none", "--quiet"]) == 0
    assert not (out / "stale.txt").exists() and (out / "report.json").is_file()
    assert json.loads((out / "report.json").read_text())["held"] == {}


def test_maps_neither_fitted_nor_held_stay_at_the_prior_and_say_so(capture, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "out"
    assert main(["fit", str(capture), "--out", str(out), "--maps", "none", "--fit", "roughness"]) == 0
    err = capsys.readouterr().err
    for name in ("base_color", "metallic"):
        assert f"pbrfit: note: {name} is neither fitted nor held" in err
    report = json.loads((out / "report.json").read_text())
    assert report["held"] == {"base_color": {"source": "prior", "value": [0.5, 0.5, 0.5]},
                              "metallic": {"source": "prior", "value": 0.0}}
    assert report["material"]["base_color"] == [0.5, 0.5, 0.5] and report["material"]["metallic"] == 0.0


def test_fit_refuses_an_out_folder_it_did_not_write(capture, tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    assert main(["fit", str(capture), "--out", str(out), "--maps", "none", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(out) in err[0] and "no .pbrfit-output of kind 'fit'" in err[0]
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    assert main(["fit", str(capture), "--out", str(a_file), "--maps", "none", "--quiet"]) == 2
    assert "not a folder" in capsys.readouterr().err and a_file.read_text() == "x"


def test_fit_with_a_broken_truth_folder_warns_and_fits(capture, tmp_path, capsys, monkeypatch):
    import shutil

    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    cap = tmp_path / "cap"
    shutil.copytree(capture, cap)
    for f in (cap / "truth").glob("base_color.*"):
        f.unlink()
    out = tmp_path / "out"
    assert main(["fit", str(cap), "--out", str(out), "--maps", "none", "--quiet"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "warning" in err[0] and "truth" in err[0]
    assert "truth_rmse" not in json.loads((out / "report.json").read_text())


@pytest.mark.parametrize(
    "extra,message",
    [
        (["--fit", "normals"], "unknown map 'normals'"),
        (["--fit", "albedo"], "unknown map 'albedo'"),
        (["--fit", "roughness,base_color,roughness"], "--fit: lists roughness twice"),
        (["--roughness", "1.5"], "--roughness: expected values in [0, 1], got 1.5"),
        (["--base-color", "1,2"], "--base-color: expected R,G,B in [0, 1], got '1,2'"),
        (["--base-color", "0.5,2,0.5"], "--base-color: expected values in [0, 1], found 0.5 to 2"),
        (["--metallic", "nan"], "--metallic: holds NaN or inf"),
        (["--fit", "base_color", "--base-color", "0.5,0.5,0.5"], "--fit: lists base_color, which --base-color holds too"),
        (["--fit", "roughness", "--roughness", "0.3"], "--fit: lists roughness, which --roughness holds too"),
        (["--base-color", "0.5,0.5,0.5", "--metallic", "0", "--roughness", "0.3"], "--fit: nothing to fit (every map is held fixed)"),
        (["--resolution", "0"], "--resolution: must be an integer from 1 to 8192, got 0"),
        (["--resolution", "100000"], "--resolution: must be an integer from 1 to 8192, got 100000"),
        (["--roughness-from", "/no/such/folder"], "--roughness-from: /no/such/folder: material folder not found"),
        (["--roughness-from", __file__], f"--roughness-from: {__file__}: is a file, not a material folder"),
        (["--devices", "99"], "(the devices JAX sees), got 99"),
        (["--devices", "0"], "(the devices JAX sees), got 0"),
        (["--devices", "two"], "expected auto or 1 to"),
        (["--smooth", "nan"], "--smooth: must be a finite number >= 0, got nan"),
        (["--continuation", "abc"], "--continuation: expected 'none' or comma-separated weights >= 0 within float32, got 'abc'"),
        (["--fit", ""], "--fit: nothing to fit (it names no map)"),
        (["--fit", " , "], "--fit: nothing to fit (it names no map)"),
        (["--continuation", "0.01,-1"], "weights >= 0 within float32, got '0.01,-1'"),
        (["--pixel-samples", "0"], "--pixel-samples: expected auto or 1 to 4, got 0"),
        (["--pixel-samples", "5"], "--pixel-samples: expected auto or 1 to 4, got 5"),
        (["--pixel-samples", "two"], "--pixel-samples: expected auto or 1 to 4, got two"),
        (["--pixel-samples", "\u00b2"], "--pixel-samples: expected auto or 1 to 4, got \u00b2"),
        (["--smooth", "1e39"], "--smooth: must be at most 3.4e+38 (float32), got 1e+39"),
        (["--cg-rtol", "0.001", "--solver", "lm"], "--cg-rtol: only the structured solver uses it, not --solver lm"),
        (["--continuation", "0.0035,0.00035", "--solver", "lm"], "--continuation: only the structured solver uses it"),
        (["--continuation", "0.0035,0.00035", "--maps", "none"], "--continuation: --maps none fits one uniform"),
        (["--continuation", "1e40"], "--continuation: expected 'none' or comma-separated weights >= 0 within float32, got '1e40'"),
        (["--rtol", "-1"], "--rtol: must be a finite number >= 0, got -1.0"),
        (["--atol", "inf"], "--atol: must be a finite number >= 0, got inf"),
        (["--cg-rtol", "0"], "--cg-rtol: must be a number in (0, 1), got 0.0"),
        (["--cg-rtol", "1.5"], "--cg-rtol: must be a number in (0, 1), got 1.5"),
        (["--cg-rtol", "nan"], "--cg-rtol: must be a number in (0, 1), got nan"),
        (["--cg-rtol", "0.01", "--solver", "lm"], "--cg-rtol: only the structured solver uses it, not --solver lm"),
        (["--noise-rtol", "-0.5"], "--noise-rtol: must be a finite number >= 0, got -0.5"),
        (["--noise-rtol", "nan"], "--noise-rtol: must be a finite number >= 0, got nan"),
        (["--noise-rtol", "0.01", "--solver", "gn"], "--noise-rtol: only the structured solver uses it"),
        (["--unconstrained-sigma", "0"], "--unconstrained-sigma: must be a number > 0 (inf: hold no texel), got 0.0"),
        (["--unconstrained-sigma", "nan"], "--unconstrained-sigma: must be a number > 0 (inf: hold no texel), got nan"),
        (["--uncertainty-radius", "-1"], "--uncertainty-radius: must be an integer from 0 to 2, got -1"),
        (["--uncertainty-radius", "3"], "--uncertainty-radius: must be an integer from 0 to 2, got 3"),
        (["--uncertainty-radius", "one"], "argument --uncertainty-radius: invalid int value: 'one'"),
        (["--metallic", "0.5", "--fit", "metallic,roughness"], "--fit: lists metallic, which --metallic holds too"),
        (["--resolution", "abc"], "argument --resolution: invalid int value: 'abc'"),
        (["--solver", "bogus"], "argument --solver: invalid choice: 'bogus'"),
        (["--noise-level", "poisson"], "argument --noise-level: invalid choice: 'poisson'"),
        (["--cache", "__FILE__"], "exists and is not a folder"),
        (["--ibl", "per_pixel", "--fit", "base_color,normal"], "--ibl per_pixel: fitted normals need --ibl split_sum"),
        (["--ibl", "per_pixel", "--ibl-samples", "0"], "--ibl-samples: must be between 1 and 1048576, got 0"),
        (["--ibl", "per_pixel", "--ibl-levels", "1"], "--ibl-levels: must be between 2 and 256, got 1"),
        (["--ibl", "per_pixel", "--ibl-levels", "99999999999999999999"],
         "--ibl-levels: must be between 2 and 256, got 99999999999999999999"),
        (["--max-steps", "99999999999999999999999"], "--max-steps: must be an integer from 1 to 1000000, got 9999"),
        (["--ibl", "exact"], "argument --ibl: invalid choice: 'exact'"),
        (["--occlusion", "sometimes"], "argument --occlusion: invalid choice: 'sometimes'"),
        (["--roughness", "0.3", "--roughness-from", "__HELD__"],
         "--roughness-from: --roughness holds roughness at a value too; give one of the two"),
        (["--roughness-from", "__OUT__"], "holds the roughness map of --roughness-from"),
        (["--continuation", "0.01", "--solver", "lm"], "--continuation: only the structured solver uses it, not --solver lm"),
        (["--ibl-samples", "64", "--ibl", "split_sum"], "--ibl-samples: only per-pixel integrals use it (--ibl per_pixel, or auto where it chooses them)"),
        (["--ibl-levels", "5", "--ibl", "split_sum"], "--ibl-levels: only per-pixel integrals use it (--ibl per_pixel, or auto where it chooses them)"),
        (["--bounce", "off", "--ibl", "split_sum"], "--bounce: only per-pixel integrals with occlusion use it (not with --ibl split_sum)"),
        (["--bounce", "on", "--occlusion", "off"], "--bounce: only per-pixel integrals with occlusion use it (not with --occlusion off)"),
        (["--bounce", "sometimes"], "argument --bounce: invalid choice: 'sometimes'"),
        (["--maps", "none", "--resolution", "8"], "--resolution: --maps none fits one uniform material"),
        (["--maps", "none", "--smooth", "0.1"], "--smooth: --maps none fits one uniform material"),
        (["--maps", "none", "--coarse-to-fine"], "--coarse-to-fine: --maps none fits one uniform material"),
        (["--maps", "none", "--continuation", "0.1"], "--continuation: --maps none fits one uniform material"),
        (["--ibl-levels", "9", "--ibl", "split_sum"], "--ibl-levels: only per-pixel integrals use it (--ibl per_pixel, or auto where it chooses them)"),
        (["--model", "diffuse=burly"], "--model: unknown Model.diffuse 'burly'; expected one of 'lambert', 'burley'"),
        (["--model", "burley"], "--model: expected KEY=VALUE pairs separated by commas, got 'burley'"),
        (["--model", "shine=1"], "--model: unknown field 'shine'; expected one of distribution, geometry"),
        (["--model", "specular=maybe"], "--model: specular must be true or false, got 'maybe'"),
        (["--model", "ior=0.5"], "--model: Model.ior must be a finite number >= 1, got 0.5"),
        (["--model", "diffuse=burley,diffuse=none"], "--model: diffuse is given twice"),
        (["--model", "metallic=false"], "--model: metallic=False has no metal lobe, and metallic is fitted"),
    ],
)
def test_bad_fit_options_exit_2_and_write_nothing(capture, tmp_path, capsys, extra, message):
    from pbrfit.io.images import write_image

    out = tmp_path / "out"
    (tmp_path / "a_file").write_text("")
    (tmp_path / "held").mkdir()
    write_image(tmp_path / "held" / "roughness.exr", np.full((1, 1, 1), 0.4, np.float32))
    if "__OUT__" in extra:  # an earlier fit's folder, read from and written to: it would be replaced
        out = tmp_path / "held"
        (out / ".pbrfit-output").write_text("fit\n")
    before = sorted(p.name for p in out.iterdir()) if out.exists() else None
    paths = {"__FILE__": tmp_path / "a_file", "__HELD__": tmp_path / "held", "__OUT__": out}
    extra = [str(paths.get(e, e)) for e in extra]
    assert main(["fit", str(capture), "--out", str(out), "--quiet", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pbrfit: error: ") and message in err[0]
    assert (sorted(p.name for p in out.iterdir()) if out.exists() else None) == before


def test_model_option_fits_a_capture_rendered_with_that_brdf(capture, tmp_path, monkeypatch):
    """A capture rendered with Burley diffuse (`render --model diffuse=burley`) is fitted exactly
    with the matching model (`fit --model diffuse=burley`, recorded in report.json), and not
    with the default Lambert one: the BRDF variant reaches the render and the fit."""
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    burley = tmp_path / "burley"
    assert main(["render", str(capture), "--material", str(capture / "truth"), "--out", str(burley),
                 "--model", "diffuse=burley", "--quiet"]) == 0
    lambert, _ = read_image(capture / "images" / "000.exr")
    rendered, _ = read_image(burley / "images" / "000.exr")
    assert np.abs(rendered[..., :3] - lambert[..., :3]).max() > 1e-3  # the two BRDFs differ here
    reports = {}
    for name, extra in (("burley", ["--model", "diffuse=burley"]), ("lambert", [])):
        out = tmp_path / f"fit-{name}"
        assert main(["fit", str(burley), "--out", str(out), "--resolution", "8", "--max-steps", "30",
                     "--no-search", "--no-repair", "--no-uniform-check", "--quiet", *extra]) == 0
        reports[name] = json.loads((out / "report.json").read_text())
    assert reports["burley"]["model"]["diffuse"] == "burley" and reports["lambert"]["model"]["diffuse"] == "lambert"
    assert reports["burley"]["final_loss"] < 1e-3 * reports["lambert"]["final_loss"]


def test_options_that_mean_nothing_else_parse():
    """'none' or the default spelled out is no conflict: only what another mode would ignore is."""
    from pbrfit.cli.main import build_parser
    from pbrfit.cli.fit import fit_options

    parse = lambda *extra: fit_options(build_parser().parse_args(["fit", "cap", "--out", "o", *extra]))
    assert parse("--solver", "lm", "--continuation", "none").continuation == ()
    assert parse("--maps", "none", "--continuation", "none", "--smooth", "0").maps == "none"
    assert parse("--ibl", "per_pixel", "--ibl-samples", "64").pixel_ibl_settings.samples == 64
    assert parse("--bounce", "off").occlusion_settings.bounce == "off"
    assert parse().occlusion_settings.bounce == "auto" and parse("--bounce", "on").occlusion_settings.bounce == "on"


def test_fit_continuation_option(capture, tmp_path, monkeypatch):
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    reports = {}
    for value in ("0.01,0.001", "none"):
        out = tmp_path / value
        assert main(["fit", str(capture), "--out", str(out), "--resolution", "8", "--max-steps", "26",
                     "--continuation", value, "--quiet"]) == 0
        reports[value] = json.loads((out / "report.json").read_text())
    cont = reports["0.01,0.001"]["continuation"]
    assert cont["relative"] == [0.01, 0.001] and len(cont["weights"]) == 2
    # the weights are the relative ones times the data's curvature; the steps ran under them
    np.testing.assert_allclose(cont["weights"], [0.01 * cont["curvature"], 0.001 * cont["curvature"]], rtol=1e-5)
    assert cont["weights"][0] > cont["weights"][1] > 0 and 0 < cont["steps"] < 26
    assert reports["none"]["continuation"] is None


def test_fit_pixel_samples_option(capture, tmp_path, monkeypatch):
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "out"
    assert main(["fit", str(capture), "--out", str(out), "--maps", "none", "--pixel-samples", "2", "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["pixel_samples"] == 2 and report["resolution"] == [1, 1] and report["pixels"] > 0
    assert all(np.isfinite(report["psnr"]))


def test_fit_missing_capture_exits_2(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["fit", str(tmp_path / "nope"), "--out", str(out)]) == 2
    assert capsys.readouterr().err.strip() == f"pbrfit: error: {tmp_path / 'nope'}: capture not found"
    assert not out.exists()


def test_a_truncated_png_is_one_line_of_error(tmp_path, capfd, monkeypatch):
    """libpng prints its own "libpng error: ..." to the process's standard error before
    OpenImageIO fails: the command's error stays one line (its own, naming the file). Standard
    error is file descriptor 2 here, as in a command (``capfd`` reads the descriptor)."""
    import io
    import sys

    monkeypatch.setattr(sys, "stderr", io.TextIOWrapper(open(2, "wb", buffering=0, closefd=False), write_through=True))
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    cap = tmp_path / "cap"
    assert main(["synth", "peer-plane", "--out", str(cap), "--size", "16", "--views", "1", "--texture-size", "4",
                 "--format", "png8", "--quiet"]) == 0
    frame = cap / json.loads((cap / "capture.json").read_text())["frames"][0]["file_path"]
    data = frame.read_bytes()
    frame.write_bytes(data[: len(data) // 2])
    out = tmp_path / "out"
    capfd.readouterr()
    assert main(["fit", str(cap), "--out", str(out), "--quiet"]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pbrfit: error: ") and str(frame) in err[0], err
    assert not out.exists()


def test_fit_a_capture_mixing_exr_and_png_frames(tmp_path, monkeypatch):
    # color space by file type, frame by frame (the spec's default): two of four frames re-saved
    # as 16-bit sRGB PNGs; the maps are still recovered exactly
    from pbrfit.physics.color import linear_to_srgb
    from pbrfit.io.images import write_image

    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    cap = tmp_path / "cap"
    assert main(["synth", "peer-plane", "--out", str(cap), "--size", "48", "--views", "4", "--texture-size", "16",
                 "--quiet"]) == 0
    data = json.loads((cap / "capture.json").read_text())
    data["images"].pop("color_space", None)
    for frame in data["frames"][::2]:
        image, _ = read_image(cap / frame["file_path"])
        (cap / frame["file_path"]).unlink()
        frame["file_path"] = frame["file_path"].rsplit(".", 1)[0] + ".png"
        write_image(cap / frame["file_path"], np.asarray(linear_to_srgb(np.clip(image[..., :3], 0.0, 1.0))), "uint16")
    (cap / "capture.json").write_text(json.dumps(data))
    out = tmp_path / "out"
    assert main(["fit", str(cap), "--out", str(out), "--resolution", "16", "--no-search", "--no-repair",
                 "--no-uniform-check", "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert max(report["truth_rmse"].values()) < 1e-3, report["truth_rmse"]
    # sRGB frames: the default tried 2 x 2 samples too, and kept the centres the images were rendered at
    assert report["footprint"]["selected"] == 1 and report["pixel_samples"] == 1


def _broken_copy(capture, tmp_path, edit):
    import shutil

    cap = tmp_path / "cap"
    shutil.copytree(capture, cap)
    data = json.loads((cap / "capture.json").read_text())
    edit(data, cap)
    (cap / "capture.json").write_text(json.dumps(data))
    return cap


def _all_masks_zero(data, cap):
    from pbrfit.io.images import write_image

    for frame in data["frames"]:
        if "mask_path" in frame:
            write_image(cap / frame["mask_path"], np.zeros((32, 32, 1), np.float32), "uint8")


def _lights_off(data, cap):
    for light in data.get("lights", []):
        light["intensity"] = 0.0


def _lights_off_under_a_black_sky(data, cap):
    from pbrfit.io.images import write_image

    _lights_off(data, cap)
    write_image(cap / "black.exr", np.zeros((8, 16, 3), np.float32), "float")
    data["environment"] = {"file": "black.exr"}


@pytest.mark.parametrize(
    "edit,message",
    [(_all_masks_zero, "no usable pixels"), (_lights_off, "no light reaches the mesh"),
     (_lights_off_under_a_black_sky, "black.exr is black, and every light is off")],
)
def test_captures_that_leave_nothing_to_fit_exit_2(capture, tmp_path, capsys, monkeypatch, edit, message):
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    cap = _broken_copy(capture, tmp_path, edit)
    out = tmp_path / "out"
    assert main(["fit", str(cap), "--out", str(out), "--maps", "none", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and "capture.json" in err[0]
    assert not out.exists()


def test_a_frame_with_no_usable_pixel_is_named(capture, tmp_path, capsys, monkeypatch):
    """A camera that looks away from the mesh contributes nothing: the fit goes on without it,
    and says which frame (its PSNR was null in report.json, without a word)."""
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))

    def look_away(data, cap):
        data["frames"][1]["transform_matrix"][0][3] += 1e6

    cap = _broken_copy(capture, tmp_path, look_away)
    out = tmp_path / "out"
    assert main(["fit", str(cap), "--out", str(out), "--maps", "none", "--max-steps", "5", "--quiet"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pbrfit: warning: ") and "frames[1] (" in err[0], err
    assert "no usable pixel" in err[0] and "frames[0]" not in err[0] and "frames[2]" not in err[0]


def test_uniform_fit_of_a_mesh_without_uvs_and_a_map_held_from_a_folder(capture, tmp_path, monkeypatch, capsys):
    import shutil

    import trimesh

    from pbrfit.io.images import read_image, write_image

    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))

    def strip_uv(data, cap):
        mesh = trimesh.load(cap / data["mesh"], force="mesh")
        trimesh.Trimesh(mesh.vertices, mesh.faces).export(cap / data["mesh"])

    cap = _broken_copy(capture, tmp_path, strip_uv)
    held = tmp_path / "held"
    held.mkdir()
    write_image(held / "metallic.exr", np.zeros((1, 1, 1), np.float32))  # only the held map
    out = tmp_path / "out"
    assert main(["fit", str(cap), "--out", str(out), "--maps", "none", "--metallic-from", str(held), "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["fitted"] == ["base_r", "base_g", "base_b", "roughness"]
    assert report["material"]["metallic"] == 0.0 and (out / "material.glb").is_file()
    # the uniform material renders on the same mesh: 1 x 1 maps need no texture coordinates
    rendered = tmp_path / "rendered"
    assert main(["render", str(cap), "--material", str(out), "--out", str(rendered), "--quiet"]) == 0
    image, _ = read_image(rendered / json.loads((rendered / "capture.json").read_text())["frames"][0]["file_path"])
    assert np.isfinite(image).all() and image[..., :3].max() > 0
    textured = tmp_path / "textured"
    shutil.copytree(out, textured)
    write_image(textured / "base_color.exr", np.full((2, 2, 3), 0.5, np.float32))
    assert main(["render", str(cap), "--material", str(textured), "--out", str(tmp_path / "r2"), "--quiet"]) == 2
    assert "has no texture coordinates" in capsys.readouterr().err and not (tmp_path / "r2").exists()
    shutil.rmtree(textured)
    shutil.copytree(out, textured)  # a uniform material with an emissive map reads texture coordinates too
    write_image(textured / "emissive.exr", np.zeros((2, 2, 3), np.float32))
    assert main(["render", str(cap), "--material", str(textured), "--out", str(tmp_path / "r2"), "--quiet"]) == 2
    assert "has no texture coordinates" in capsys.readouterr().err and not (tmp_path / "r2").exists()
    shutil.rmtree(out)
    # texture maps still need texture coordinates: a one-line error before any work
    assert main(["fit", str(cap), "--out", str(out), "--quiet"]) == 2
    assert not out.exists()


def test_per_pixel_ibl_fit_of_a_monte_carlo_capture(tmp_path, monkeypatch, capsys):
    """A capture whose environment light was rendered by the Monte Carlo reference, fitted with
    per-pixel integrals: the options reach the fit and the report says how it was lit."""
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    cap, out = tmp_path / "cap", tmp_path / "out"
    assert main(["synth", "sphere-env", "--out", str(cap), "--size", "24", "--views", "3", "--texture-size", "4",
                 "--ibl", "monte_carlo", "--ibl-samples", "64", "--quiet"]) == 0
    synth = json.loads((cap / "truth" / "synth.json").read_text())
    assert synth["model"]["ibl"] == "monte_carlo" and "64 samples" in synth["ibl_settings"]
    assert main(["fit", str(cap), "--out", str(out), "--maps", "none", "--ibl", "per_pixel", "--ibl-samples", "32",
                 "--ibl-levels", "5", "--pixel-samples", "1", "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["model"]["ibl"] == "per_pixel"
    assert report["ibl"]["mode"] == "per_pixel" and report["ibl"]["samples"] == 32 and report["ibl"]["levels"] == 5
    assert report["ibl"]["seconds"] > 0 and len(report["psnr"]) == 3 and all(np.isfinite(report["psnr"]))
    assert len(list((tmp_path / "cache").glob("pixel-ibl-*.npy"))) == 1  # cached with the G-buffers
    # occlusion is auto by default with per-pixel integrals; a lone sphere casts no shadow on itself
    assert report["occlusion"]["mode"] == "auto" and not report["occlusion"]["used"]
    assert report["occlusion"]["reason"] == "no face has the mesh above it"
    assert not list((tmp_path / "cache").glob("visibility-*.npy"))


def test_per_pixel_ibl_without_an_environment_warns_and_fits(capture, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "out"
    assert main(["fit", str(capture), "--out", str(out), "--maps", "none", "--ibl", "per_pixel", "--quiet"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--ibl per_pixel" in err[0] and "has no environment" in err[0]
    report = json.loads((out / "report.json").read_text())
    assert report["model"]["ibl"] is None and "ibl" not in report


def test_summary_line_names_the_footprint():
    from types import SimpleNamespace

    from pbrfit.cli.fit import fit_summary

    report = dict(resolution=[8, 8], solver="structured", steps=30, final_loss=2.0, wall_time=5.0,
                  times=dict(compile=1.0), pixel_samples=2,
                  footprint=dict(selected=2, energies={"2": 2.0, "1": 3.5}, pixels=10))
    line = fit_summary(SimpleNamespace(report=report), {})
    assert "2x2 samples per pixel (auto: data loss 2.000e+00 against 3.500e+00 at centres)" in line
    report.update(pixel_samples=1, footprint=dict(selected=1, energies={"2": 3.5, "1": 2.0}, pixels=10))
    assert "pixel centres (auto: data loss 2.000e+00 against 3.500e+00 with 2x2)" in fit_summary(
        SimpleNamespace(report=report), {})
    report.update(pixel_samples=3, footprint=dict(selected=3, energies={"3": 2.0, "1": 3.5}, pixels=10))
    assert "3x3 samples per pixel (auto: data loss 2.000e+00 against 3.500e+00 at centres)" in fit_summary(
        SimpleNamespace(report=report), {})
    report.update(pixel_samples=1, footprint=dict(selected=1, skipped="too many"))
    assert "pixel centres (auto: the footprint's samples skipped, too many pixels)" in fit_summary(
        SimpleNamespace(report=report), {})
    report.pop("footprint")
    assert "samples" not in fit_summary(SimpleNamespace(report=report), {})
    assert "5.0 s (compile 1.0 s)" in fit_summary(SimpleNamespace(report=report), {})
    report["times"]["compile_background"] = 6.5
    assert "5.0 s (compile 1.0 s, 6.5 s more overlapped)" in fit_summary(SimpleNamespace(report=report), {})
    assert "uniform" not in fit_summary(SimpleNamespace(report=report), {})
    assert "unseen" not in fit_summary(SimpleNamespace(report=dict(report, unseen_texels=0)), {})
    assert ", 7 of 64 texels unseen (not fitted: coverage 0)" in fit_summary(
        SimpleNamespace(report=dict(report, unseen_texels=7)), {})
    report["uniform_check"] = dict(metallic=dict(uniform=True, value=0.0), roughness=dict(uniform=False))
    assert "30 steps, loss 2.000e+00, one value for metallic 0 (uniform check); " in fit_summary(
        SimpleNamespace(report=report), {})
    assert "repair" not in fit_summary(SimpleNamespace(report=report), {})
    report["repair"] = dict(passes=[
        dict(flagged=5, moved=12, clusters=3, clusters_kept=2, texels_kept=8, energy_before=4.0, energy_after=2.5,
             kept=True),
        dict(flagged=2, moved=6, clusters=1, clusters_kept=1, texels_kept=6, energy_before=2.5, energy_after=2.0,
             kept=True),
        dict(flagged=1, moved=4, clusters=1, clusters_kept=0, texels_kept=0, energy_before=2.0, kept=False)])
    assert ", repair re-solved 14 texels in 3 clusters (loss 4.000e+00 -> 2.000e+00)" in fit_summary(
        SimpleNamespace(report=report), {})
    report["repair"]["passes"] = report["repair"]["passes"][1:]
    assert ", repair re-solved 6 texels in 1 cluster (loss 2.500e+00 -> 2.000e+00)" in fit_summary(
        SimpleNamespace(report=report), {})
    # --noise-level estimated: the repair was the first fit's, whose loss the summary gives too
    report["noise_level"] = dict(mode="estimated", sigma=[0.01, 0.02], first_fit=dict(final_loss=2.0))
    assert (", the first fit's repair re-solved 6 texels in 1 cluster (loss 2.500e+00 -> 2.000e+00), weighted by "
            "the estimated noise level (0.01 to 0.02; first fit loss 2.000e+00)") in fit_summary(
        SimpleNamespace(report=report), {})


def test_the_progress_line_says_which_stage_runs_and_keeps_only_steps_in_the_history():
    """Between the solver's steps (reported when each run ends) the line names the stage that
    began, with where the fit is; only the steps' entries go to the loss history."""
    from pbrfit.cli.fit import FitProgress, describe

    at = dict(level=0, resolution=(64, 64))
    assert describe(dict(at, stage="search")) == "level 0 (64x64)  search"
    assert describe(dict(at, stage="solving", repair=2)) == "level 0 (64x64)  repair 2  solving"
    assert describe(dict(at, step=12, loss=1.5e-3)) == "level 0 (64x64) step  12  loss 1.5000e-03"
    assert describe(dict(at, step=12, budget=40, loss=1.5e-3)) == "level 0 (64x64) step  12/40  loss 1.5000e-03"
    assert describe(dict(stage="ibl", done=1200, total=5000)) == "per-pixel IBL 1,200 / 5,000 pixels"
    progress = FitProgress(False)
    for entry in (dict(at, stage="grid start"), dict(at, step=0, loss=2.0), dict(at, stage="standard errors")):
        progress(entry)
    assert [h["loss"] for h in progress.history] == [2.0]


def test_loss_history_keeps_the_kept_footprint_only():
    from pbrfit.cli.fit import loss_history

    steps = [dict(loss=9.0), dict(loss=5.0), dict(loss=4.0, footprint=1), dict(loss=3.0, footprint=1),
             dict(loss=2.0, footprint=2)]
    assert loss_history(steps, dict(footprint=dict(selected=2))) == [
        dict(step=0, loss=9.0), dict(step=1, loss=5.0), dict(step=2, loss=2.0)]
    assert [h["loss"] for h in loss_history(steps, dict(footprint=dict(selected=1)))] == [9.0, 5.0, 4.0, 3.0]
    assert [h["loss"] for h in loss_history(steps[:2], {})] == [9.0, 5.0]


def test_loss_history_keeps_the_weighted_fit_only():
    from pbrfit.cli.fit import loss_history

    steps = [dict(loss=9.0), dict(loss=5.0, footprint=1), dict(loss=4.0, footprint=2), dict(loss=3.0, repair=1),
             dict(loss=2.5, weighted=True), dict(loss=2.0, weighted=True, repair=1)]
    report = dict(footprint=dict(selected=2), repair=dict(passes=[dict(kept=True)]))
    assert [h["loss"] for h in loss_history(steps, report)] == [2.5, 2.0]
    assert [h["step"] for h in loss_history(steps, report)] == [0, 1]
    assert [h["loss"] for h in loss_history(steps[:4], report)] == [9.0, 4.0, 3.0]


def test_loss_history_keeps_kept_repair_passes_only():
    from pbrfit.cli.fit import loss_history

    steps = [dict(loss=9.0), dict(loss=5.0), dict(loss=3.0, repair=1), dict(loss=4.0, repair=2)]
    passes = [dict(flagged=3, kept=True), dict(flagged=2, kept=False)]
    assert [h["loss"] for h in loss_history(steps, dict(repair=dict(passes=passes)))] == [9.0, 5.0, 3.0]
    assert [h["loss"] for h in loss_history(steps, dict(repair=dict(skipped="a uniform material")))] == [9.0, 5.0]


def test_loss_history_keeps_uniform_check_refits_only_where_kept():
    from pbrfit.cli.fit import loss_history

    steps = [dict(loss=9.0), dict(loss=5.0), dict(loss=6.0, check="metallic"), dict(loss=5.5, check="metallic"),
             dict(loss=7.0, check="roughness")]
    checks = dict(metallic=dict(uniform=True), roughness=dict(uniform=False))
    assert [h["loss"] for h in loss_history(steps, dict(uniform_check=checks))] == [9.0, 5.0, 6.0, 5.5]
    assert [h["loss"] for h in loss_history(steps, dict(uniform_check=dict(metallic=dict(uniform=False))))] == [
        9.0, 5.0]
    assert [h["loss"] for h in loss_history(steps[:2], dict(uniform_check=dict(skipped="a uniform material")))] == [
        9.0, 5.0]


def test_no_uniform_check_option_reaches_the_fit():
    from pbrfit.cli.main import build_parser
    from pbrfit.cli.fit import fit_options

    def options(*extra):
        return fit_options(build_parser().parse_args(["fit", "CAP", "--out", "OUT", *extra]))

    assert options().uniform_check is True and options("--no-uniform-check").uniform_check is False


def test_cg_rtol_option_reaches_the_fit():
    from pbrfit.cli.main import build_parser
    from pbrfit.cli.fit import fit_options

    def options(*extra):
        return fit_options(build_parser().parse_args(["fit", "CAP", "--out", "OUT", *extra]))

    assert options("--cg-rtol", "0.01").cg_rtol == 0.01
    assert options().cg_rtol == FitOptions().cg_rtol  # the library's default, CG_RTOL
    assert options("--noise-rtol", "0").solver.noise_rtol == 0.0 and options("--noise-rtol", "0.1").noise_rtol == 0.1
    assert options().solver.noise_rtol == FitOptions().solver.noise_rtol == NOISE_RTOL


def test_loss_scale_option_reaches_the_fit():
    from pbrfit.cli.main import build_parser
    from pbrfit.cli.fit import fit_options
    from pbrfit.errors import CaptureError

    def options(*extra):
        return fit_options(build_parser().parse_args(["fit", "CAP", "--out", "OUT", *extra]))

    assert options("--loss", "cauchy", "--loss-scale", "0.2").loss_scale == 0.2
    assert options("--loss", "huber").loss_scale == FitOptions().loss_scale  # the library's default, LOSS_SCALE
    for extra, message in ((("--loss-scale", "0.2"), "--loss-scale: only a robust loss uses it"),
                           (("--loss", "huber", "--loss-scale", "0"), "--loss-scale: must be a finite number > 0"),
                           (("--loss", "huber", "--loss-scale", "nan"), "--loss-scale: must be a finite number > 0")):
        with pytest.raises(CaptureError, match=message):
            options(*extra)


def test_uncertainty_radius_option_reaches_the_fit():
    from pbrfit.cli.main import build_parser
    from pbrfit.cli.fit import fit_options

    def options(*extra):
        return fit_options(build_parser().parse_args(["fit", "CAP", "--out", "OUT", *extra]))

    assert options("--uncertainty-radius", "0").uncertainty_radius == 0
    assert options("--uncertainty-radius", "2").uncertainty_radius == 2
    assert options().uncertainty_radius == FitOptions().uncertainty_radius  # the library's default, WINDOW_RADIUS


def test_unconstrained_sigma_option_reaches_the_fit():
    from pbrfit.cli.main import build_parser
    from pbrfit.cli.fit import fit_options

    def options(*extra):
        return fit_options(build_parser().parse_args(["fit", "CAP", "--out", "OUT", *extra]))

    assert options("--unconstrained-sigma", "0.2").unconstrained_sigma == 0.2
    assert options("--unconstrained-sigma", "inf").unconstrained_sigma == float("inf")
    assert options().unconstrained_sigma == FitOptions().unconstrained_sigma  # the library's default, UNCONSTRAINED_SIGMA


def test_solve_options_reach_the_fit():
    """--smooth, --rtol, --atol, --coarse-to-fine, --no-search and --no-repair each reach the
    fit's option, given or not; not given, they are the library's own defaults."""
    from pbrfit.cli.main import build_parser
    from pbrfit.cli.fit import fit_options

    def options(*extra):
        return fit_options(build_parser().parse_args(["fit", "CAP", "--out", "OUT", *extra]))

    keys = ("smooth", "rtol", "atol", "coarse_to_fine", "search", "repair")
    assert {k: getattr(options(), k) for k in keys} == {k: getattr(FitOptions(), k) for k in keys}
    given = options("--smooth", "0.25", "--rtol", "1e-3", "--atol", "2e-4", "--coarse-to-fine", "--no-search",
                    "--no-repair")
    assert {k: getattr(given, k) for k in keys} == dict(smooth=0.25, rtol=1e-3, atol=2e-4, coarse_to_fine=True, search=False,
                                               repair=False)


@pytest.mark.parametrize("error", [MemoryError("Unable to allocate 74.5 GiB for an array"),
                                   RuntimeError("RESOURCE_EXHAUSTED: Out of memory allocating 1 bytes.\nmore")])
def test_out_of_memory_is_one_line_and_exit_2(capture, tmp_path, capsys, monkeypatch, error):
    import pbrfit.cli.main

    def fail(args):
        raise error

    monkeypatch.setitem(pbrfit.cli.main._COMMANDS, "fit", fail)
    assert main(["fit", str(capture), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pbrfit: error: out of memory: ") and "--resolution" in err[0]
    monkeypatch.setitem(pbrfit.cli.main._COMMANDS, "fit", lambda args: 1 / 0)  # anything else is a bug: it propagates
    with pytest.raises(ZeroDivisionError):
        main(["fit", str(capture), "--out", str(tmp_path / "out"), "--quiet"])


def test_a_capture_too_bright_for_float32_is_refused_not_written(capture, tmp_path, monkeypatch, capsys):
    # every value is finite float32, but a hot pixel of 1e20 overflows the solve's squares: the
    # fit would write NaN standard errors under a loss that looks perfect
    import shutil

    from pbrfit.io.images import read_image, write_image

    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    hot = tmp_path / "hot"
    shutil.copytree(capture, hot)
    pixels, _ = read_image(hot / "images" / "000.exr")
    pixels[16, 16, :3] = 1e20
    write_image(hot / "images" / "000.exr", pixels, "float")
    out = tmp_path / "out"
    assert main(["fit", str(hot), "--out", str(out), "--resolution", "8", "--max-steps", "8", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "000.exr: frames[0]: pixel value 1e+20 at row 16, column 16 is too bright for the float32 solve" in err, err
    assert err.count("\n") == 1 and not out.exists()
    # past that check, the solve's loss overflows: it says so (its residuals at the start are
    # returned, not zeros that would read as a perfect fit), and the fit is refused after it
    import pbrfit.fitting.api

    with monkeypatch.context() as m:
        m.setattr(pbrfit.fitting.api, "_check_brightness", lambda capture: None)
        assert main(["fit", str(hot), "--out", str(out), "--resolution", "8", "--max-steps", "8", "--no-search",
                     "--no-repair", "--no-uniform-check", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "the fit's loss came out NaN or beyond float32" in err and err.count("\n") == 1 and not out.exists(), err
    # a light that bright: the fit comes out NaN, and is refused after it
    shutil.copy(capture / "images" / "000.exr", hot / "images" / "000.exr")
    data = json.loads((hot / "capture.json").read_text())
    data["lights"][0]["intensity"] = 1e20
    (hot / "capture.json").write_text(json.dumps(data))
    assert main(["fit", str(hot), "--out", str(out), "--resolution", "8", "--max-steps", "8", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "came out NaN or beyond float32" in err and err.count("\n") == 1 and not out.exists(), err



def test_devices_auto_is_one_device_on_the_cpu():
    from pbrfit.cli.fit import fit_devices

    assert fit_devices("auto") is None and fit_devices("1") is None  # one device: no mesh


def test_quality_rungs_set_the_options_not_given():
    """--quality draft|default|best (`pbrfit.fitting.defaults.QUALITY`) fills the options the
    command line leaves out; a flag given with it wins, and a rung leaves what only the
    structured solver reads to it."""
    from pbrfit.cli.main import build_parser
    from pbrfit.cli.fit import fit_options
    from pbrfit.fitting.defaults import QUALITY

    def options(*extra):
        return fit_options(build_parser().parse_args(["fit", "CAP", "--out", "OUT", *extra]))

    def rung(o):
        return {name: getattr(o, name) for name in {**QUALITY["draft"], **QUALITY["best"]}}

    assert rung(options()) == rung(options("--quality", "default")) == rung(FitOptions())
    draft = options("--quality", "draft")
    assert draft.quality == "draft" and rung(draft) == rung(FitOptions(quality="draft"))
    assert {name: getattr(draft, name) for name in QUALITY["draft"]} == QUALITY["draft"]
    assert draft.solver.cg_rtol == QUALITY["draft"]["cg_rtol"] and draft.continuation is None
    assert options("--quality", "draft", "--cg-rtol", "0.01").cg_rtol == 0.01
    assert options("--quality", "draft", "--continuation", "0.01").continuation == (0.01,)
    assert draft.pixel_samples == 1 and options().pixel_samples == "auto"
    assert options("--quality", "draft", "--pixel-samples", "auto").pixel_samples == "auto"
    best = options("--quality", "best")
    assert (best.max_steps, best.solver.rtol) == (QUALITY["best"]["max_steps"], QUALITY["best"]["rtol"])
    assert options("--quality", "best", "--max-steps", "7").max_steps == 7
    assert best.solver.noise_rtol == 0.0 and options("--quality", "best", "--noise-rtol", "0.1").noise_rtol == 0.1
    lm = options("--quality", "draft", "--solver", "lm")
    assert lm.search is False and lm.cg_rtol is None and lm.continuation == FitOptions().continuation
    # the Python API: keywords given win, a copy keeps its values, an unknown rung is refused
    assert FitOptions(quality="draft", search=True).search is True
    assert FitOptions(quality="draft").replace(max_steps=5).search is False
    with pytest.raises(ValueError, match="quality must be one of draft, default, best"):
        FitOptions(quality="fast")


def test_a_draft_fit_runs_no_stage_and_says_so(capture, tmp_path, monkeypatch):
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "out"
    assert main(["fit", str(capture), "--out", str(out), "--resolution", "8", "--quality", "draft", "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["quality"] == "draft" and report["cg_rtol"] == 0.1 and report["continuation"] is None
    assert report["stopping"]["rtol"] == 1e-3 and report["stopping"]["max_steps"] == 20
    assert report["noise_rtol"] == NOISE_RTOL
    assert [s["ran"] for s in report["stages"]] == [False, False, True], report["stages"]
