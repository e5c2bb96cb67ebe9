"""Write a diagnosis as ``report.json`` (machine-readable), ``report.md`` with plots, and ``report.html``.

Everything is written into a temporary folder beside the target and renamed into place,
so an interrupted run never leaves a half-written report.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from crisp_gym.atomic import atomic_directory
from crisp_gym.html_report import markdown_section, write_html_report
from crisp_gym.sim2real.diagnose import HELDOUT_LOGS, Diagnosis

EXTRAPOLATION_RATIO = 1.5
"""Held-out joint speeds more than this factor above (or below) the fitted ones are flagged."""
PLOT_LABEL_CHARS = 50
"""Candidate labels longer than this are cut on the plots (``report.md`` has them whole)."""
REPORT_KEYS = ("verdict", "where", "ranking", "selected", "gap_before", "gap_after_heldout", "shrink")


def write_report(result: Diagnosis, out_dir: str | Path, plots: bool = True) -> Path:
    """Write ``report.json``, ``report.md``, PNG plots and ``report.html`` (the Markdown with its
    plots, to open in a browser) into ``out_dir``."""
    out_dir = Path(out_dir)
    with atomic_directory(out_dir, overwrite=True) as tmp:
        (tmp / "report.json").write_text(json.dumps(result.to_json(), indent=1, default=_jsonable))
        figures = _plots(result, tmp) if plots else []
        text = _markdown(result, figures)
        (tmp / "report.md").write_text(text)
        title, _, body = text.partition("\n")
        write_html_report(tmp / "report.html", title.lstrip("# "), [markdown_section("Diagnosis", body)],
                          subtitle="crisp gap diagnose")
    return out_dir


def _jsonable(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not serialisable: {type(x)}")


def _fmt(x: float | None, digits: int = 4) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{digits}g}"


def extrapolation_lines(result: Diagnosis) -> list[str]:
    """A warning when the held-out joints move at other speeds than the fitted ones: the held-out
    gap then also measures the fit's extrapolation (``holdout_blocks`` spreads a split log's
    held-out data over it)."""
    ratio = result.heldout_speed_ratio
    if 1 / EXTRAPOLATION_RATIO <= ratio <= EXTRAPOLATION_RATIO:
        return []
    split_at_end = result.heldout != HELDOUT_LOGS and result.config.get("holdout_blocks", 1) == 1
    hint = (" If the log's excitation changes over time (a sweep), `--config.holdout-blocks 3` holds out data "
            "spread over it." if split_at_end else "")
    return [f"The held-out joints move {ratio:.2g} times as fast as the fitted ones (median over joints): the "
            f"held-out gap also measures how the fitted model extrapolates.{hint}"]


def _indistinguishable_lines(sel: dict) -> list[str]:
    """The candidates of other families these logs cannot tell from the selected (or closest) one."""
    others = sel["indistinguishable"]
    if not others:
        return []
    named = ", ".join(f"{o['effect']} ({_fmt(o['gap_heldout'])} rad)" for o in others)
    return [f"These logs cannot tell it from {named}: their held-out gaps differ by less than the noise floor. "
            "A log that moves the joints (or the contacts) where these effects act differently would decide."]


def _markdown(result: Diagnosis, figures: list[str]) -> str:
    sel = result.selected or result.closest
    lines = ["# Sim-to-real gap diagnosis", ""]
    verdict = result.verdict
    if verdict == "none":
        lines.append(f"**Verdict: no significant gap.** The held-out gap ({_fmt(result.gap_before)} rad RMS) is "
                     f"at the noise floor ({_fmt(result.noise_floor)} rad).")
    elif verdict == "explained":
        lines.append(f"**Verdict: {sel['effect']}** explains the gap: held-out RMS {_fmt(result.gap_before)} → "
                     f"{_fmt(result.gap_after_heldout)} rad (shrink {100 * result.shrink:.0f} %, "
                     f"noise floor {_fmt(result.noise_floor)} rad, {_fmt(result.noise_floor_best)} rad "
                     f"with the selected effect); margin over the runner-up "
                     f"({sel['runner_up']}): {_fmt(100 * (sel['margin_over_runner_up'] or 0), 3)} % in score.")
        if sel["shares"]:
            lines.append("Shares of what it removes: " + ", ".join(
                f"{s['effect']} {100 * s['share']:.0f} %" for s in sel["shares"]) + ".")
        lines += _indistinguishable_lines(sel)
    else:
        closest_shrink = 1.0 - sel["gap_heldout"] / result.gap_before if result.gap_before > 0 else 0.0
        lines.append(f"**Verdict: unexplained.** No effect in the library brings the held-out gap "
                     f"({_fmt(result.gap_before)} rad) near the noise floor ({_fmt(result.noise_floor)} rad). "
                     f"The closest candidate, {sel['effect']}, leaves {_fmt(sel['gap_heldout'])} rad "
                     f"({100 * closest_shrink:.0f} % shrink); it is the nearest model, not a cause: an effect "
                     f"outside the library can be imitated by a mix of others.")
        lines += _indistinguishable_lines(sel)
        lines += ["", *_residual_lines(result.residual)]
    lines += ["", f"Held out: {result.heldout}.", *extrapolation_lines(result), ""]
    if sel:
        lines += ["## Parameters (95 % confidence)", "", "| effect | parameter | value | CI | unit |", "|---|---|---|---|---|"]
        for p in sel["parameters"]:
            flag = (" **not determined by the data**" if p.get("identified") is False
                    else " **at its bound**" if p.get("at_bound") else "")
            lines.append(f"| {p['effect']} | {p['name']} | {_fmt(p['value'])}{flag} | [{_fmt(p['ci95'][0])}, "
                         f"{_fmt(p['ci95'][1])}] | {p['unit']} |")
        lines.append("")
        if any(p.get("at_bound") and p.get("identified") is not False for p in sel["parameters"]):
            lines += ["A parameter at its bound means the fit wanted to go further: the effect is likely not the "
                      "cause, or only part of it.", ""]
        if any(p.get("identified") is False for p in sel["parameters"]):
            lines += ["A parameter not determined by the data changes nothing these logs see (its interval is its "
                      "whole range): any value of it fits as well.", ""]
    w = result.where
    lines += ["## Where the gap lies", "", f"Worst joint: **{w['worst_joint']}**.", "",
              "| joint | RMS pos (rad) | floor | RMS vel (rad/s) | lag real vs cmd (s) | lag sim vs cmd (s) | "
              "extra lag real vs sim (s) |", "|---|---|---|---|---|---|---|"]
    for j, v in w["per_joint"].items():
        lines.append(f"| {j} | {_fmt(v['rms_pos'])} | {_fmt(v['floor'])} | {_fmt(v['rms_vel'])} | "
                     f"{_fmt(v['lag_real_vs_command_s'])} | {_fmt(v['lag_sim_vs_command_s'])} | "
                     f"{_fmt(v['lag_real_vs_sim_s'])} |")
    lines += ["", "| regime | share of samples | RMS (rad) | ratio to overall |", "|---|---|---|---|"]
    for k, v in w["regimes"].items():
        lines.append(f"| {k} | {100 * v['share_of_samples']:.0f} % | {_fmt(v['rms'])} | {_fmt(v['ratio_to_overall'], 3)} |")
    lines += ["", "## Ranking (held-out)", "",
              "| # | effect | params | train gap | held-out gap | shrink | gap / floor |", "|---|---|---|---|---|---|---|"]
    for i, r in enumerate(result.ranking, 1):
        lines.append(f"| {i} | {r['effect']} | {r['nparam']} | {_fmt(r['gap_train'])} | {_fmt(r['gap_heldout'])} | "
                     f"{100 * r['shrink']:.0f} % | {_fmt(r['gap_over_floor'], 3)} |")
    lines.append("")
    if result.skipped:
        lines += ["## Candidates that cannot act on these logs (skipped)", ""]
        lines += [f"- {s['effect']}: {s['reason']}" for s in result.skipped]
        lines.append("")
    if result.mujoco_warnings:
        lines += ["## MuJoCo's warnings during the fits", "",
                  "Trial parameters under which a replay window diverged: MuJoCo resets such a window, which "
                  "then counts with a large gap. Expected while fitting.", ""]
        lines += [f"- {count} × {message}" for message, count in result.mujoco_warnings.items()]
        lines.append("")
    for f in figures:
        lines += [f"![{f}]({f})", ""]
    return "\n".join(lines)


def _residual_lines(residual: dict | None) -> list[str]:
    """What the closest candidate leaves, in words (an unexplained verdict's ``residual``)."""
    if not residual:
        return []
    joints = ", ".join(f"{j['joint']} ({100 * j['share_of_excess']:.0f} %)" for j in residual["joints"]) or "none"
    band = max(residual["bands"], key=lambda b: b["share_of_power"])
    upper = "up" if band["to_hz"] is None else f"{band['to_hz']:g} Hz"
    regime = residual["strongest_regime"]
    ratio = residual["regimes"].get(regime) if regime else None
    return [f"What remains: excess over the noise floor on {joints}; "
            f"{100 * band['share_of_power']:.0f} % of its power between {band['from_hz']:g} Hz and {upper}; "
            + (f"strongest in `{regime}` ({_fmt(ratio, 3)} × its overall RMS)." if regime else "no regime stands out.")]


def _plots(result: Diagnosis, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rp = result.replay
    names = result.joints
    sel = result.selected or result.closest
    files = []

    def cut(label: str) -> str:  # a per-joint mixture's label lists every joint (the tables have it whole)
        return label if len(label) <= PLOT_LABEL_CHARS else label[:PLOT_LABEL_CHARS - 1] + "…"

    # Overlay: the held-out windows of the worst joint with the largest gap before.
    j = names.index(result.where["worst_joint"])
    err = np.sqrt(np.sum((rp.pred_before[..., j] - rp.target[..., j]) ** 2 * rp.mask, axis=1))
    fig, axes = plt.subplots(1, min(3, len(err)), figsize=(12, 3.2), squeeze=False)
    for ax, k in zip(axes[0], np.argsort(err)[::-1]):
        n = int(rp.mask[k].sum())
        t = rp.dt * np.arange(1, n + 1)
        ax.plot(t, rp.target[k, :n, j], "k", label="real")
        ax.plot(t, rp.pred_before[k, :n, j], "C3--", label="sim before")
        ax.plot(t, rp.pred_after[k, :n, j], "C2", label=cut(f"sim + {sel['effect']}") if sel else "sim after")
        ax.set_xlabel("time in window (s)")
        ax.set_title(f"{names[j]}, window {k}", fontsize=9)
    axes[0][0].set_ylabel("position (rad)")
    # below the panels: inside one, a joint model's label squeezed the panels and covered an axis
    fig.legend(*axes[0][0].get_legend_handles_labels(), loc="lower center", ncols=3, fontsize=8)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.savefig(out / "overlay.png", dpi=90)
    plt.close(fig)
    files.append("overlay.png")

    per = result.where["per_joint"]
    after = (sel or {}).get("per_joint_gap_after", {})
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(max(5, 0.6 * len(names) + 2), 3.2))
    ax.bar(x - 0.25, [per[n]["rms_pos"] for n in names], 0.25, label="before (all windows)")
    ax.bar(x, [after.get(n, np.nan) for n in names], 0.25, label="after (held-out)")
    ax.bar(x + 0.25, [per[n]["floor"] for n in names], 0.25, label="noise floor")
    ax.set_xticks(x, names, rotation=60, ha="right", fontsize=8)
    ax.set_ylabel("RMS position gap (rad)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "per_joint.png", dpi=90)
    plt.close(fig)
    files.append("per_joint.png")

    reg = result.where["regimes"]
    fig, ax = plt.subplots(figsize=(6, 3))
    ax.bar(list(reg), [v["ratio_to_overall"] for v in reg.values()])
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_ylabel("RMS gap / overall")
    ax.tick_params(axis="x", rotation=30, labelsize=8)
    fig.tight_layout()
    fig.savefig(out / "regimes.png", dpi=90)
    plt.close(fig)
    files.append("regimes.png")

    rank = result.ranking[:12]
    fig, ax = plt.subplots(figsize=(7, 0.3 * len(rank) + 1.2))
    labels = [cut(r["effect"]) for r in rank]
    ax.barh(labels[::-1], [r["gap_heldout"] for r in rank][::-1])
    ax.axvline(result.gap_before, color="C3", label="before")
    ax.axvline(result.noise_floor, color="k", ls="--", label="noise floor")
    ax.set_xlabel("held-out RMS gap (rad)")
    ax.xaxis.set_major_locator(plt.MaxNLocator(4))  # gaps' tick labels are long
    ax.tick_params(axis="y", labelsize=7)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "ranking.png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    files.append("ranking.png")
    return files
