"""A campaign's printed summary (the paper's table 1 layout, every method) and campaign.png."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from northfinder.estimators.campaign_stats import ARCMIN_PER_DEG

SHORT = {
    "exact": "exact",
    "coordinate_transform": "coord. transform",
    "vector": "vector",
    "eq11": "eq 11",
    "uncompensated": "uncompensated",
}


def _am(v: float | None, fmt: str = "+.3f") -> str:
    return "—" if v is None else f"{v:{fmt}}′"


def _deg(v: float | None, fmt: str = ".4f") -> str:
    return "—" if v is None else f"{v:{fmt}}"


def print_campaign(state: dict[str, Any], console: Any = None) -> None:
    """Table 1 of the paper, one column per method: each find's deviation from its reference
    [arc min], then mean (= deviation from the reference), std, RMS, max; then degrees and σ."""
    from rich.console import Console

    if console is None:
        console = Console()
        if not console.is_terminal:
            console = Console(width=max(console.width, 150))
    console.print(_arcmin_table(state))
    console.print(_degrees_table(state))
    if len(state.get("steps", [])) > 1:
        console.print(_steps_table(state))


def _arcmin_table(state: dict[str, Any]) -> Any:
    """Each find's deviation per method [arc min] and the statistics rows (the paper's table 1)."""
    from rich.markup import escape
    from rich.table import Table

    stats, runs, main = state.get("statistics", {}), state["runs"], state["method"]
    methods = list(stats)
    t = Table(title=escape("campaign: heading − reference azimuth [arc min] (layout of the paper's table 1)"))
    t.add_column("find")
    t.add_column(escape("reference [°]"), justify="right")
    for m in methods:
        t.add_column(SHORT.get(m, m) + (" *" if m == main else ""), justify="right")
    t.add_column(escape(f"σ reported ({main})"), justify="right")
    for r in runs:
        cells = [
            _am(float((r["methods"][m] - r["reference_deg"] + 180) % 360 - 180) * ARCMIN_PER_DEG)
            for m in methods
        ]
        t.add_row(
            r["run_dir"],
            f"{r['reference_deg']:.3f}",
            *cells,
            _am(r["heading_std_deg"] * ARCMIN_PER_DEG, ".3f"),
        )
    t.add_section()
    for label, key, fmt in (
        ("mean (deviation from reference)", "mean_arcmin", "+.3f"),
        ("standard deviation", "std_arcmin", ".3f"),
        ("RMS", "rms_arcmin", ".3f"),
        ("max |deviation|", "max_abs_arcmin", ".3f"),
        ("mean reported σ", "mean_reported_sigma_arcmin", ".3f"),
    ):
        t.add_row(label, "", *(_am(stats[m].get(key), fmt) for m in methods), "")
    t.add_row(
        "std / mean reported σ",
        "",
        *(_deg(stats[m].get("observed_over_reported"), ".2f") for m in methods),
        "",
    )
    return t


def _degrees_table(state: dict[str, Any]) -> Any:
    """Every method's statistics in degrees."""
    from rich.markup import escape
    from rich.table import Table

    stats, runs = state.get("statistics", {}), state["runs"]
    d = Table(title=f"every method in degrees ({len(runs)} finds)")
    for col in ("method", "mean [°]", "std [°]", "RMS [°]", "max |dev| [°]", "mean σ [°]", "std/σ"):
        d.add_column(escape(col), justify="right" if col != "method" else "left")
    for m in stats:
        s = stats[m]
        d.add_row(
            m,
            _deg(s.get("mean_deg"), "+.5f"),
            _deg(s.get("std_deg"), ".5f"),
            _deg(s.get("rms_deg"), ".5f"),
            _deg(s.get("max_abs_deg"), ".5f"),
            _deg(s.get("mean_reported_sigma_deg"), ".5f"),
            _deg(s.get("observed_over_reported"), ".2f"),
        )
    return d


def _steps_table(state: dict[str, Any]) -> Any:
    """The main method per base heading (a campaign of more than one step)."""
    from rich.markup import escape
    from rich.table import Table

    st = Table(title=f"{state['method']} per base heading")
    for col in ("step", "reference [°]", "n", "mean [′]", "std [′]", "mean σ [′]"):
        st.add_column(escape(col), justify="right")
    for s in state.get("steps", []):
        st.add_row(
            str(s["step"] + 1),
            f"{s['reference_deg']:.3f}",
            str(s["n"]),
            _am(s.get("mean_arcmin")),
            _am(s.get("std_arcmin"), ".3f"),
            _am(s.get("mean_reported_sigma_arcmin"), ".3f"),
        )
    return st


def write_figure(state: dict[str, Any], path: str | Path) -> Path:
    """campaign.png: the main method's deviation per find with its ±1σ bar against the reference
    (0), a histogram of the deviations with the normal curve of the mean reported σ, and every
    method's mean ± std and RMS side by side."""
    import matplotlib.pyplot as plt

    fig = draw_figure(state)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def draw_figure(state: dict[str, Any]) -> Any:
    """campaign.png's figure (write_figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2, a3) = plt.subplots(1, 3, figsize=(16, 5.6), gridspec_kw={"width_ratios": [2.2, 1.2, 1.4]})
    _finds_panel(a1, state)
    _histogram_panel(a2, state)
    _methods_panel(a3, state)
    fig.suptitle(campaign_title(state), fontsize=11)
    fig.tight_layout()
    return fig


def _finds(n: int) -> str:
    return f"{n} find" if n == 1 else f"{n} finds"


def campaign_title(state: dict[str, Any]) -> str:
    """The figure's title: unit, UTC date, grade and seed (simulated) or the real bench, the plan."""
    sim = state.get("simulate") or {}
    when = str(state.get("started_utc") or "")[:16].replace("T", " ")
    plan = state["plan"]
    src = f"simulated, grade {sim.get('grade')}, seeds from {sim.get('seed')}" if sim else "real bench"
    return (f"northfinder campaign — unit {state.get('unit') or 'not given'}, {when} UTC, {src}; "
            f"{_finds(len(state['runs']))} of {plan['positions']} positions × {plan['dwell_s']:g} s, "
            f"method {state['method']}")


def _finds_panel(a1: Any, state: dict[str, Any]) -> None:
    """The main method's deviation per find with its reported ±1σ, against the reference (0)."""
    import matplotlib.ticker

    runs, main, stats = state["runs"], state["method"], state["statistics"]
    dev = np.array([r["error_deg"] for r in runs]) * ARCMIN_PER_DEG
    sig = np.array([r["heading_std_deg"] for r in runs]) * ARCMIN_PER_DEG
    steps = np.array([r["step"] for r in runs])
    x = np.arange(1, len(runs) + 1)
    for s in sorted(set(steps.tolist())):
        k = steps == s
        ref = state["plan"]["steps"][s]["reference_deg"]
        a1.errorbar(x[k], dev[k], yerr=sig[k], fmt="o", capsize=3, label=f"step {s + 1}: reference {ref:g}°")
    a1.axhline(0.0, color="k", lw=1, label="reference azimuth")
    m = stats[main]
    a1.axhline(m["mean_arcmin"], color="C3", ls="--", lw=1, label=f"mean {m['mean_arcmin']:+.3f}′")
    if len(runs) <= 20:  # every find numbered (MaxNLocator gives 0.9, 1.0, 1.1 … around a single one)
        a1.set_xticks(x)
    else:
        a1.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    a1.set_xlim(0.5, len(runs) + 0.5)
    a1.set_xlabel("find (plan order)")
    a1.set_ylabel(f"{main} heading − reference [arc min] (bar: reported 1σ)")
    a1.set_title(
        f"{_finds(len(runs))}, {state['plan']['positions']} positions × {state['plan']['dwell_s']:g} s"
    )
    a1.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=3)
    a1.grid(True, alpha=0.3)


HISTOGRAM_MIN_FINDS = 10
"""Fewer finds than this are drawn one by one (a rug), not as a histogram of spikes."""


def _histogram_panel(a2: Any, state: dict[str, Any]) -> None:
    """The deviations against the normal curve of the mean reported σ: a histogram of counts (the
    curve scaled to counts per bin) from HISTOGRAM_MIN_FINDS finds on, each find as a tick below."""
    main = state["method"]
    m = state["statistics"][main]
    dev = np.array([r["error_deg"] for r in state["runs"]]) * ARCMIN_PER_DEG
    s0 = m.get("mean_reported_sigma_arcmin") or 0.0
    lo, hi = min(dev.min(), m["mean_arcmin"] - 3 * s0), max(dev.max(), m["mean_arcmin"] + 3 * s0)
    if len(dev) >= HISTOGRAM_MIN_FINDS:
        bins = np.linspace(lo, hi, max(5, min(20, len(dev) // 2)) + 1)
        a2.hist(dev, bins=bins, alpha=0.6, label=f"finds ({len(dev)})")
        scale = len(dev) * (bins[1] - bins[0])
        a2.set_ylabel("finds per bin")
    else:
        scale = 1.0
        a2.set_ylabel("density of N(mean, reported σ) [1/arc min]")
    if s0:
        g = np.linspace(lo, hi, 200)
        curve = scale * np.exp(-0.5 * ((g - m["mean_arcmin"]) / s0) ** 2) / (s0 * np.sqrt(2 * np.pi))
        a2.plot(g, curve, color="C1", label=f"N(mean, reported σ {s0:.3f}′)")
    top = a2.get_ylim()[1]
    a2.plot(dev, np.full(dev.shape, -0.04 * top), "|", color="C0", ms=14, mew=1.5,
            label=f"each find ({len(dev)})" if len(dev) < HISTOGRAM_MIN_FINDS else "each find")
    a2.set_ylim(-0.09 * top, top * 1.05)
    a2.set_xlabel(f"{main} deviation [arc min]")
    std = m.get("std_arcmin")
    a2.set_title(f"observed std {std:.3f}′ vs reported σ {s0:.3f}′" if std is not None else
                 f"1 find: no spread yet (reported σ {s0:.3f}′)")
    a2.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, frameon=False)
    a2.grid(True, alpha=0.3)


def _methods_panel(a3: Any, state: dict[str, Any]) -> None:
    """Every method's mean ± std and RMS side by side (a method far off scale written in)."""
    stats = state["statistics"]
    names = list(stats)
    xi = np.arange(len(names))
    shown = ~_clip_outliers(a3, xi, names, stats)  # the off-scale ones are written in, not drawn
    means = np.array([stats[n]["mean_arcmin"] for n in names])
    stds = np.array([stats[n]["std_arcmin"] or 0.0 for n in names])
    rms = np.array([stats[n]["rms_arcmin"] for n in names])
    a3.errorbar(xi[shown] - 0.1, means[shown], yerr=stds[shown], fmt="o", capsize=4, label="mean ± std")
    a3.plot(xi[shown] + 0.1, rms[shown], "s", label="RMS")
    a3.axhline(0.0, color="k", lw=1)
    a3.set_xlim(-0.6, len(names) - 0.25)  # room for an off-scale box at the last place
    a3.set_xticks(xi, [SHORT.get(n, n) for n in names], rotation=30, ha="right")
    a3.set_ylabel("deviation from reference [arc min]")
    a3.set_title("every method")
    a3.legend(fontsize=8)
    a3.grid(True, alpha=0.3)


def _clip_outliers(ax: Any, xi: np.ndarray, names: list[str], stats: dict[str, Any]) -> np.ndarray:
    """Scale the method panel to the methods within 5× of the best one's extent; a method far
    off (the uncompensated one on a tilted table) is written in as text inside the panel at its
    place. Returns which methods are off scale."""
    extent = [abs(stats[n]["mean_arcmin"]) + (stats[n]["std_arcmin"] or 0.0) for n in names]
    extent = [max(e, stats[n]["rms_arcmin"]) for e, n in zip(extent, names, strict=True)]
    limit = 5.0 * min(extent)
    off = np.array([e > limit for e in extent])
    if not off.any():
        return off
    lim = 1.15 * max(e for e in extent if e <= limit)
    ax.set_ylim(-lim, lim)
    for x, n, e in zip(xi, names, extent, strict=True):
        if e > limit:
            s = stats[n]
            ax.text(
                x,
                0.0,
                f"off scale:\nmean {s['mean_arcmin']:+.1f}′\nstd {_am(s['std_arcmin'], '.1f')}\n"
                f"RMS {s['rms_arcmin']:.1f}′",
                ha="center",
                va="center",
                fontsize=7,
                bbox={"facecolor": "white", "alpha": 0.8},
            )
    return off
