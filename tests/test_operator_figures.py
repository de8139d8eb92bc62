"""Every figure an operator reads — the find's report.png, campaign.png, the swaying and GNSS
reports and the tools/ figures — drawn from a stored run (tests/data/reports) and checked for its
text: the title naming run, plan and result, axis labels with units, legend entries."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

DATA = Path(__file__).resolve().parent / "data" / "reports"
ROOT = Path(__file__).resolve().parents[1]


def texts(fig) -> dict[str, list[str]]:
    """The figure's text elements by kind."""
    out: dict[str, list[str]] = {"suptitle": [], "title": [], "xlabel": [], "ylabel": [], "legend": [],
                                 "text": [], "xtick": []}
    if fig._suptitle is not None:
        out["suptitle"].append(fig._suptitle.get_text())
    for ax in fig.axes:
        out["title"].append(ax.get_title())
        out["xlabel"].append(ax.get_xlabel())
        out["ylabel"].append(ax.get_ylabel())
        leg = ax.get_legend()
        if leg is not None:
            out["legend"] += [t.get_text() for t in leg.get_texts()]
        out["text"] += [t.get_text() for t in ax.texts]
        out["xtick"] += [t.get_text() for t in ax.get_xticklabels()]
    plt.close(fig)
    return out


def has(items: list[str], *words: str) -> bool:
    return any(all(w in item for w in words) for item in items)


def test_find_report_names_run_plan_result_and_labels_every_panel():
    from northfinder.report import draw_report, run_info

    run = DATA / "find-r5"
    result = json.loads((run / "result.json").read_text())
    t = texts(draw_report(result, samples=None, info=run_info(run)))
    (title,) = t["suptitle"]
    for word in ("run find-r5", "UTC", "plan positions+motion, 8 × 5 s", "grade nav, seed 1",
                 "heading 36.9529°", "± 0.0567°", "truth 37.0000°", "error -0.0471°"):
        assert word in title, (word, title)
    assert has(t["title"], "heading of each fit")
    assert has(t["title"], "every gyro sample")
    assert has(t["text"], "no per-sample fit")  # no raw samples stored: the panel says so
    assert has(t["legend"], "position mean ± 1σ") and has(t["legend"], "R + a·cos α + b·sin α")
    assert has(t["text"], "truth 37.000°")
    assert sum("table angle α [deg]" in x for x in t["xlabel"]) == 6  # every residual strip
    assert has(t["ylabel"], "residual", "[deg/h]") and has(t["ylabel"], "residual", "[mg]")
    assert has(t["xlabel"], "heading − 36.953° [deg]", "1σ")
    assert has(t["text"], "dwell means alone 37.0480° ± 0.0947°")


def test_find_report_with_every_sample_the_fit_used():
    """The sample panel from a run's placed samples: rest and motion per gyro axis, the table angle."""
    from northfinder.report import draw_report, run_info

    run = DATA / "find-r5"
    result = json.loads((run / "result.json").read_text())
    rate_hz, n = 1000.0, 4000
    alpha = np.repeat(np.arange(4) * 90.0, n // 4) + np.linspace(0, 90, n) % 1.0
    omega = np.where(np.arange(n) % 1000 < 600, 0.0, 10.0)
    gyro = np.column_stack([np.cos(np.deg2rad(alpha)), np.sin(np.deg2rad(alpha)), np.full(n, 9.5)]) * 10
    samples = {"alpha_deg": alpha, "omega_dps": omega, "gyro_dph": gyro, "rate_hz": rate_hz}
    t = texts(draw_report(result, samples=samples, info=run_info(run)))
    assert has(t["legend"], "gyro y, rest (2400 samples)")
    assert has(t["legend"], "gyro y, motion (1600 samples)")
    assert has(t["legend"], "table angle α")
    assert has(t["ylabel"], "table angle α [deg]")
    assert has(t["xlabel"], "device time from the first dwell [s]")


def test_campaign_figure_title_finds_as_ticks_and_off_scale_method_written_in():
    from northfinder.cli._campaign_report import draw_figure

    state = json.loads((DATA / "campaign_two_finds.json").read_text())
    t = texts(draw_figure(state))
    (title,) = t["suptitle"]
    for word in ("unit not given", "2026-11-25 22:18 UTC", "grade nav", "2 finds of 4 positions × 3 s"):
        assert word in title, (word, title)
    assert has(t["legend"], "each find (2)")  # 2 finds: ticks, not a density histogram
    assert has(t["legend"], "N(mean, reported σ")
    assert has(t["title"], "observed std", "reported σ")
    assert has(t["text"], "off scale", "mean -76.9′")
    assert has(t["ylabel"], "[arc min]")


def test_campaign_figure_of_a_single_find():
    """One find: no spread yet (std None) — the figure still draws and says so."""
    from northfinder.cli._campaign_report import draw_figure

    state = json.loads((DATA / "campaign_two_finds.json").read_text())
    state["runs"] = state["runs"][:1]
    for s in state["statistics"].values():
        s["std_arcmin"] = None
    t = texts(draw_figure(state))
    assert has(t["title"], "1 find: no spread yet")
    assert has(t["text"], "off scale", "std —")


def test_swaying_report_zooms_the_sway_and_names_the_residual_axes():
    from northfinder.report import draw_swaying_report

    result = json.loads((DATA / "swaying_result.json").read_text())
    resid = dict(np.load(DATA / "swaying_report.npz"))
    t = texts(draw_swaying_report(result, resid))
    (title,) = t["suptitle"]
    assert "align --mode swaying (cone)" in title and "truth" in title and "error" in title
    assert has(t["title"], "first 40 s of 300 s")
    assert has(t["ylabel"], "RMS per 5 s [deg/s]")
    assert has(t["legend"], "z of the initial body frame (mean +31.4 µg)")
    assert not has(t["legend"], "i_b0")
    assert has(t["title"], "accelerometer's bias")


def test_gnss_report_plain_symlog_labels_and_truth_in_title():
    from northfinder.report import draw_gnss_report

    result = json.loads((DATA / "gnss_result.json").read_text())
    hist = dict(np.load(DATA / "gnss_report.npz"))
    fig = draw_gnss_report(result, hist)
    fig.canvas.draw()
    ticks = [tl.get_text() for tl in fig.axes[0].get_yticklabels()]
    t = texts(fig)
    assert "truth 90.000°" in t["suptitle"][0] and "error -0.005°" in t["suptitle"][0]
    assert "10" in ticks and "0.1" in ticks and not any("^" in x or "$" in x for x in ticks), ticks
    assert has(t["legend"], "sincos error") and has(t["legend"], "lever arm x")
    assert has(t["ylabel"], "lever arm [m] (dashed: truth)")


def _tool(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_tools_accuracy_figures_have_grouped_cells_and_units(tmp_path):
    tool = _tool("accuracy_vs_limit")
    rng = np.random.default_rng(1)
    white = tool.white_grid(rng, 40)
    t = texts(tool.plot_ratio_vs_limit(white, 40, tmp_path / "ratio_vs_limit.png"))
    assert has(t["xlabel"], "latitude L [°]", "n positions, T_total, ARW")
    assert has(t["legend"], "within ±5 % of 1") and has(t["legend"], "σ_MC / σ_limit, tilt 10°")
    assert has(t["text"], "n 24", "600 s", "°/√h")
    drift = [(8, 120.0, 0.002, 0.05, 0.08, {k: 0.1 + 0.01 * i for i, k in enumerate(tool.DRIFT_KEYS)})]
    fig = tool.plot_drift(drift, 40, tmp_path / "drift.png")
    assert all(len(line.get_xdata()) == 1 for line in fig.axes[0].get_lines())  # no line joins cells
    t = texts(fig)
    assert has(t["xtick"], "120 s", "0.002 °/√h", "0.05 °/h/√h")
    assert has(t["legend"], "drift-aware (linear bias), interleaved order")
    assert (tmp_path / "drift.png").stat().st_size > 10_000
