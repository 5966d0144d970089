"""One map per case, like the paper's Fig. 3: the truth trees as circles of their crown
width, each method's detections as markers, the robot's path; metres from the twin's
origin (UTM offsets)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, no screen
import matplotlib.pyplot as plt
from matplotlib.patches import Circle

from treetraits.evaluation.cases import Case
from treetraits.evaluation.metrics import Detection, TruthTree
from treetraits.sim.paths import drive, waypoints
from treetraits.sim.run import ORIGIN_UTM

MARKERS = {
    "paper": ("x", "tab:red"),
    "robust": ("+", "tab:blue"),
    "rph": ("^", "tab:orange"),
    "rph-vlp16": ("v", "tab:purple"),
}


def plot_case(
    path: Path,
    case: Case,
    seed: int,
    truths: Sequence[TruthTree],
    detections: dict[str, Sequence[Detection]],
) -> None:
    e0, n0 = ORIGIN_UTM
    fig, ax = plt.subplots(figsize=(9, 6.5), dpi=110)
    settings = case.settings(seed)
    poses = drive(
        waypoints(settings.path, settings.width, settings.length, settings.goal), settings.drive
    )
    ax.plot(poses[:, 1], poses[:, 2], color="0.6", lw=1, ls="--", label="robot path")
    for t in truths:
        x, y = t.easting - e0, t.northing - n0
        if t.kind == "missing":  # in the field map, not planted
            ax.plot(x, y, marker="X", color="0.4", ms=7)
            ax.annotate(
                f"{t.tree_id} missing",
                (x, y),
                xytext=(0, 5),
                textcoords="offset points",
                ha="center",
                fontsize=7,
                color="0.3",
            )
            continue
        ax.add_patch(Circle((x, y), t.width_m / 2, fc=(0.2, 0.6, 0.2, 0.18), ec="tab:green"))
        ax.plot(x, y, marker="o", color="tab:green", ms=4)
        # Id and row above the crown: neighbours 4 m apart leave no room beside it.
        ax.annotate(
            f"{t.tree_id} {t.row}",
            (x, y + t.width_m / 2),
            xytext=(0, 2),
            textcoords="offset points",
            ha="center",
            fontsize=7,
            color="darkgreen",
        )
    ax.plot([], [], marker="o", color="tab:green", ls="none", label="truth (circle: crown width)")
    for method, found in detections.items():
        marker, colour = MARKERS.get(method, ("s", "k"))
        placed = [d for d in found if d.easting is not None]
        ax.scatter(
            [d.easting - e0 for d in placed],
            [d.northing - n0 for d in placed],
            marker=marker,
            s=60,
            color=colour,
            lw=1.5,
            zorder=3,
            label=f"{method} ({len(placed)} trees)",
        )
    ax.set_aspect("equal")
    ax.set_xlabel(f"easting - {e0:.0f} (m)")
    ax.set_ylabel(f"northing - {n0:.0f} (m)")
    ax.set_title(f"{case.title}: seed {seed}")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
