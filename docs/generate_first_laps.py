"""Draw docs/images/first_laps.png: steps to the first lap of each seed, per track and agent, from
``bench track_learning`` records (JSONL, runs that end at their first lap).

    python docs/generate_first_laps.py bench/out/track_learning-A.jsonl bench/out/track_learning-B.jsonl ...

Every run of the records is one dot; a run that never lapped is drawn at its budget as a hollow
dot. The median of each agent and track is a bar. Agents are drawn in the order they first appear.
"""

from __future__ import annotations

import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(paths: list[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bench.track_learning import first_step, load_results

    results, budgets, _ = load_results([Path(p) for p in paths])
    tracks = [t for t in ("classic", "oval", "technical") if any(tr == t for tr, _ in results)]
    agents: list[str] = []
    for _, label in results:
        if label not in agents:
            agents.append(label)
    fig, axes = plt.subplots(1, len(tracks), figsize=(4.2 * len(tracks), 3.8), sharey=True)
    axes = [axes] if len(tracks) == 1 else list(axes)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, track in zip(axes, tracks):
        for i, label in enumerate(agents):
            runs = results.get((track, label), [])
            if not runs:
                continue
            steps = [first_step(r) for r in runs]
            budget = budgets.get(track, max((s for s in steps if s is not None), default=0))
            shown = [s if s is not None else budget for s in steps]
            color = colors[i % len(colors)]
            for j, (s, lapped) in enumerate(zip(shown, [s is not None for s in steps])):
                ax.scatter(i + (j - (len(shown) - 1) / 2) * 0.06, s, s=28, color=color if lapped else "none",
                           edgecolors=color, zorder=3)
            ax.hlines(statistics.median(shown), i - 0.3, i + 0.3, color=color, lw=2.5, zorder=2)
        ax.set_title(track)
        ax.set_xticks(range(len(agents)))
        ax.set_xticklabels([a.replace("-CAP-R250", "") for a in agents], rotation=20, fontsize=8)
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_ylabel("environment steps to the first lap\n(dots: seeds; bars: medians)")
    fig.tight_layout()
    out = ROOT / "docs" / "images" / "first_laps.png"
    fig.savefig(out, dpi=110)
    print(out)


if __name__ == "__main__":
    main(sys.argv[1:])
