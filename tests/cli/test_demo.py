"""`pbrfit demo` on a small version of its scene: it synthesizes, fits and prints recovery."""

import json

import jax.numpy as jnp
import numpy as np

from pbrfit.cli.demo import CONFIDENT_SIGMA, _table, recovery_table, run_demo
from pbrfit.physics.material import Material


def test_demo_runs_end_to_end(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PBRFIT_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "demo"
    assert run_demo(str(out), size=40, views=4, texture_size=8) == 0
    text = capsys.readouterr().out
    for name in ("base_color", "metallic", "roughness", "RMSE, all", "|err| ≤ 2σ", "observed texels"):
        assert name in text, name
    assert (out / "capture" / "capture.json").is_file() and (out / "capture" / "truth").is_dir()
    for name in ("base_color.exr", "uncertainty.exr", "material.glb", "report.json", "maps.png", "views/000.png"):
        assert (out / "fit" / name).is_file(), name
    report = json.loads((out / "fit" / "report.json").read_text())
    assert set(report["truth_rmse"]) == {"base_color", "metallic", "roughness"}
    # it fitted (measured on this small scene: 0.087 / 0.179 / 0.188, the worst view's PSNR 39.9 dB)
    rmse = report["truth_rmse"]
    assert rmse["base_color"] < 0.15 and rmse["metallic"] < 0.35 and rmse["roughness"] < 0.3, rmse
    assert min(report["psnr"]) > 33.0, report["psnr"]
    # a split-sum render: the split sum's residuals are noise, and no per-pixel fit is tried
    assert report["ibl"]["mode"] == "split_sum" and not report["ibl"]["choice"]["tried"], report["ibl"]


def test_recovery_table_counts_and_calibration():
    base = jnp.full((2, 2, 3), 0.5)
    fitted = Material(base.at[0, 0].set(0.6), jnp.zeros((2, 2, 1)), jnp.full((2, 2, 1), 0.5))
    truth = Material(jnp.full((2, 2, 3), 0.5), jnp.zeros((2, 2, 1)), jnp.full((2, 2, 1), 0.5))
    sigma = np.full((2, 2, 5), 0.01, np.float32)
    sigma[0, 0, :3] = 0.2  # the wrong texel says it is unsure
    coverage = np.array([[3, 1], [1, 0]])
    rows = {r["map"]: r for r in recovery_table(fitted, truth, sigma, coverage)}
    b = rows["base_color"]
    np.testing.assert_allclose(b["rmse"], np.sqrt(0.01 / 3), rtol=1e-5)  # 1 of 3 observed texels off by 0.1
    assert b["confident"] == 2 and b["rmse_confident"] == 0.0 and 0.2 > CONFIDENT_SIGMA
    assert b["within_2sigma"] == 1.0
    # the median over the 9 observed base colour channels: six at 0.01, three at 0.2
    np.testing.assert_allclose(b["median_sigma"], 0.01, rtol=1e-6)
    assert rows["roughness"]["rmse"] == 0.0 and rows["roughness"]["confident"] == 3
    # the calibration column counts |err| <= 2σ, not 1σ or 3σ: at σ 0.2, one texel off by 0.3
    # (outside 1σ, inside 2σ) and one off by 0.5 (outside 2σ, inside 3σ), the third exact
    off = Material(base.at[0, 0].set(0.8).at[0, 1].set(1.0), jnp.zeros((2, 2, 1)), jnp.full((2, 2, 1), 0.5))
    sigma[0, 1, :3] = 0.2
    b = {r["map"]: r for r in recovery_table(off, truth, sigma, coverage)}["base_color"]
    assert b["within_2sigma"] == 6 / 9  # the exact texel's 3 channels and the 0.3 texel's 3, of 9
    np.testing.assert_allclose(b["median_sigma"], 0.2, rtol=1e-6)  # six channels at 0.2, three at 0.01


def test_recovery_table_leads_with_the_sure_texels():
    rows = [dict(map="base_color", rmse=0.0123, confident=812, rmse_confident=0.0061, median_sigma=0.011,
                 within_2sigma=0.94),
            dict(map="roughness", rmse=0.08, confident=0, rmse_confident=float("nan"), median_sigma=0.2,
                 within_2sigma=0.9)]
    head, base, rough, note = _table(rows, 1000).splitlines()
    assert head.index("sure texels") < head.index(f"RMSE, σ ≤ {CONFIDENT_SIGMA:g}") < head.index("RMSE, all")
    assert base.split() == ["base_color", "812", "0.0061", "0.0123", "0.0110", "94%"]
    assert rough.split() == ["roughness", "0", "-", "0.0800", "0.2000", "90%"]  # none sure: no RMSE to give
    assert "RMSE, all: over all 1000 observed texels" in note


def test_demo_refuses_to_replace_folders_it_did_not_write(tmp_path, capsys):
    from pbrfit.cli.main import main

    (tmp_path / "fit").mkdir()
    (tmp_path / "fit" / "thesis.tex").write_text("keep")
    assert main(["demo", "--out", str(tmp_path), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no .pbrfit-output of kind 'fit'" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit"]
    (tmp_path / "fit" / "thesis.tex").unlink()
    (tmp_path / "notes.txt").write_text("keep")  # a user's folder: nothing is written beside their files
    (tmp_path / ".fit.k2j3.tmp").mkdir()  # what a demo killed while writing leaves: not the user's
    assert main(["demo", "--out", str(tmp_path), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds what the demo did not write (notes.txt)" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == [".fit.k2j3.tmp", "fit", "notes.txt"]
