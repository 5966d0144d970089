"""The figures of `treetraits report` (treetraits/season/report.py), drawn by matplotlib as
SVG and put inline in the page.

SVG with its text kept as text (`svg.fonttype` none): the trees' labels, the axes' ticks
and units can be read, searched (Ctrl-F T17) and printed sharp at any zoom, and the
page's tests read them off the page itself. Every id of a figure is prefixed with the
figure's name, so ids stay unique in a page of several figures.
"""

from __future__ import annotations

import datetime as dt
import html
import io
import math
import re
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from treetraits.season.report import History, MapTree, RejectedObject, ReportData

# A fixed salt: the same data draws the same SVG (matplotlib's default is a random one).
SVG_RC = {"svg.fonttype": "none", "svg.hashsalt": "treetraits-report"}
NOT_MEASURED = (0.85, 0.85, 0.85, 1.0)  # a disc whose value is unknown
DAY = dt.timedelta(days=1)
# At most this many date ticks on a time axis (their labels are whole dates).
MAX_DATE_TICKS = 6


def figure(width: float, height: float) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def svg(fig: Figure, name: str, alt: str) -> str:
    """The figure as an inline `<svg>` element: no XML prolog, ids prefixed `name-`."""
    import matplotlib

    buffer = io.StringIO()
    with matplotlib.rc_context(SVG_RC):
        fig.savefig(buffer, format="svg", bbox_inches="tight", metadata={"Date": None})
    text = buffer.getvalue()
    text = text[text.index("<svg") :]
    text = re.sub(r'(?<=\s)id="', f'id="{name}-', text)
    text = text.replace('xlink:href="#', f'xlink:href="#{name}-').replace("url(#", f"url(#{name}-")
    return text.replace(
        "<svg ", f'<svg class="figure" role="img" aria-label="{html.escape(alt)}" ', 1
    )


# --- legibility ----------------------------------------------------------------------


def relative_luminance(rgb: Sequence[float]) -> float:
    """WCAG 2's relative luminance of an sRGB colour (channels 0-1)."""

    def linear(c: float) -> float:
        return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4

    r, g, b = (linear(c) for c in rgb[:3])
    return 0.2126 * r + 0.7152 * g + 0.0722 * b


def contrast_ratio(a: Sequence[float], b: Sequence[float]) -> float:
    """WCAG 2's contrast ratio (1-21; 4.5 and up: legible small text)."""
    la, lb = sorted((relative_luminance(a), relative_luminance(b)), reverse=True)
    return (la + 0.05) / (lb + 0.05)


def label_colour(face: Sequence[float]) -> str:
    """Black or white, whichever stands out more on `face`: on every colour one of the two
    has a contrast of 4.58 or more."""
    black, white = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    return "black" if contrast_ratio(face, black) >= contrast_ratio(face, white) else "white"


# --- the map -------------------------------------------------------------------------


def draw_map(data: ReportData, colour: str = "height", growth: bool = False) -> str | None:
    """The block from above, metres from its south-west corner: each found tree a disc of
    its width coloured by `colour` (or by width change per 30 days with `growth`) and
    labelled with its name in black or white (whichever reads on the disc), missing trees
    as red crosses, rejected objects as grey triangles, the robot's path as a grey line.
    None when nothing has a position (a run without a GNSS fix)."""
    placed = [t for t in data.trees if t.easting is not None and t.northing is not None]
    rejected = [r for r in data.rejected if r.easting is not None and r.northing is not None]
    if not placed and not data.path:
        return None
    points = [(t.easting, t.northing) for t in placed] + list(data.path)
    points += [(r.easting, r.northing) for r in rejected]
    e0 = math.floor(min(p[0] for p in points))
    n0 = math.floor(min(p[1] for p in points))
    fig = figure(*_map_size(points))
    ax = fig.add_subplot()
    if data.path:
        ax.plot(
            [p[0] - e0 for p in data.path],
            [p[1] - n0 for p in data.path],
            color="0.6",
            lw=1.2,
            label="robot path",
            zorder=1,
        )
    label = _draw_trees(
        ax, fig, [t for t in placed if t.status == "found"], (e0, n0), colour, growth
    )
    _draw_missing(ax, [t for t in placed if t.status == "missing"], (e0, n0))
    _draw_rejected(ax, rejected, (e0, n0))
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.margins(0.08)
    ax.set_xlabel(f"easting − {e0:.0f} (m)")
    ax.set_ylabel(f"northing − {n0:.0f} (m)")
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        _legend_below(fig, ax)
    ax.set_title("Width change per 30 days (m)" if growth else f"Trees by {label}")
    return svg(fig, "growth" if growth else "map", "growth map" if growth else "map of the block")


def _map_size(points: Sequence[tuple[float, float]]) -> tuple[float, float]:
    """Inches: the page's width, and as tall as the block's shape needs (a long row is
    not drawn in a square canvas, with a colour bar three times its height)."""
    width = 11.0
    dx = max(p[0] for p in points) - min(p[0] for p in points) + 4.0  # a crown's margin
    dy = max(p[1] for p in points) - min(p[1] for p in points) + 4.0
    return width, min(max(0.75 * width * dy / dx + 1.6, 3.2), 9.0)


def _legend_below(fig, ax) -> None:
    """The legend under the axes' labels, where it hides no tree."""
    from matplotlib.transforms import ScaledTranslation

    below = ax.transAxes + ScaledTranslation(0, -42 / 72, fig.dpi_scale_trans)
    ax.legend(
        loc="upper center",
        bbox_to_anchor=(0.5, 0.0),
        bbox_transform=below,
        ncol=3,
        fontsize=8,
        frameon=False,
    )


def _draw_trees(
    ax, fig, found: Sequence[MapTree], origin: tuple[float, float], colour: str, growth: bool
) -> str:
    """Discs of the trees' widths, each labelled; returns what the colours show."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.patches import Circle

    if growth:
        values, label, cmap = (
            [t.width_change for t in found],
            "width change (m / 30 days)",
            "RdYlGn",
        )
    elif colour == "ndvi":
        values, label, cmap = [t.ndvi for t in found], "NDVI", "RdYlGn"
    else:
        values, label, cmap = [t.height_m for t in found], "height (m)", "viridis"
    if not found:
        return label
    norm = _norm([v for v in values if v is not None], symmetric=growth)
    colours = colormaps[cmap]
    e0, n0 = origin
    for i, (t, value) in enumerate(zip(found, values, strict=True)):
        face = NOT_MEASURED if value is None or norm is None else colours(norm(value))
        centre = (t.easting - e0, t.northing - n0)
        radius = max((t.width_m or 0.3) / 2, 0.15)
        ax.add_patch(
            Circle(centre, radius, facecolor=face, edgecolor="k", lw=0.6, zorder=2, gid=f"tree-{i}")
        )
        ax.text(
            *centre,
            t.label,
            color=label_colour(face),
            fontsize=9,
            fontweight="bold",
            ha="center",
            va="center",
            zorder=3,
            gid=f"label-{i}",
        )
    mappable = ScalarMappable(norm or Normalize(0, 1), colours)
    bar = fig.colorbar(
        mappable, ax=ax, shrink=0.9, label=label if norm else f"{label}: not measured"
    )
    if norm is None:
        bar.set_ticks([])
    return label


def _norm(known: Sequence[float], symmetric: bool):
    """The colour scale over the known values (symmetric about 0 for a change); None
    when nothing is known."""
    from matplotlib.colors import Normalize

    if not known:
        return None
    low, high = min(known), max(known)
    if symmetric:
        bound = max(abs(low), abs(high), 1e-3)
        low, high = -bound, bound
    return Normalize(low, high if high > low else low + 1e-3)


def _draw_missing(ax, missing: Sequence[MapTree], origin: tuple[float, float]) -> None:
    if not missing:
        return
    e0, n0 = origin
    ax.scatter(
        [t.easting - e0 for t in missing],
        [t.northing - n0 for t in missing],
        marker="x",
        s=80,
        color="red",
        linewidths=2,
        label="missing",
        zorder=3,
    )
    for i, t in enumerate(missing):
        ax.annotate(
            t.label,
            (t.easting - e0, t.northing - n0),
            xytext=(0, 8),
            textcoords="offset points",
            color="darkred",
            fontsize=8,
            ha="center",
            va="bottom",
            zorder=3,
            gid=f"missing-{i}",
        )


def _draw_rejected(ax, rejected: Sequence[RejectedObject], origin: tuple[float, float]) -> None:
    if not rejected:
        return
    e0, n0 = origin
    ax.scatter(
        [r.easting - e0 for r in rejected],
        [r.northing - n0 for r in rejected],
        marker="^",
        s=30,
        color="0.45",
        label="rejected (not a tree)",
        zorder=1.5,  # under the crowns: what lies under a tree is listed, not drawn over it
    )


# --- distributions and histories -------------------------------------------------------

TRAITS = (("width_m", "width (m)"), ("height_m", "height (m)"), ("ndvi", "NDVI"))


def draw_histograms(trees: Sequence[MapTree]) -> str:
    """Width, height and NDVI of the found trees; the counts on whole-number ticks."""
    from matplotlib.ticker import MaxNLocator

    fig = figure(10, 3.2)
    found = [t for t in trees if t.status == "found"]
    for i, (name, label) in enumerate(TRAITS):
        ax = fig.add_subplot(1, 3, i + 1)
        ax.set_gid(f"{name}")
        values = [getattr(t, name) for t in found if getattr(t, name) is not None]
        if values:
            ax.hist(values, bins=min(12, max(3, len(values))), color="tab:green", edgecolor="k")
        else:
            ax.text(0.5, 0.5, "not measured", ha="center", va="center", transform=ax.transAxes)
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        ax.yaxis.set_gid(f"{name}-counts")
        ax.set_xlabel(label)
        ax.set_ylabel("number of trees")
    fig.tight_layout()
    return svg(fig, "histograms", "histograms of width, height and NDVI")


def draw_histories(histories: Sequence[History], survey_times_ns: Sequence[int]) -> str:
    """Width, height and NDVI of a few trees against the survey date, on an axis that spans
    the season's surveys (`date_window`) with a tick label per date."""
    from matplotlib.dates import DateFormatter, DayLocator

    lo, hi = date_window(survey_times_ns)
    interval = max(1, math.ceil((hi - lo) / DAY / MAX_DATE_TICKS))
    fig = figure(10, 3.4)
    for i, (name, label) in enumerate(TRAITS):
        ax = fig.add_subplot(1, 3, i + 1)
        ax.set_gid(f"{name}")
        bounds = []  # (time, value) of the lower bounds, all trees
        for h in histories:
            points = [
                (t, v, bound)
                for t, v, bound in zip(h.times_ns, getattr(h, name), h.bounded(name), strict=True)
                if v is not None
            ]
            if points:
                ax.plot(
                    [_utc(t) for t, _, _ in points],
                    [v for _, v, _ in points],
                    marker="o",
                    label=h.label,
                )
                bounds += [(t, v) for t, v, bound in points if bound]
        marked = _draw_lower_bounds(ax, name, bounds) if bounds else None
        ax.set_xlim(lo, hi)
        ax.xaxis.set_major_locator(DayLocator(interval=interval, tz=dt.timezone.utc))
        ax.xaxis.set_major_formatter(DateFormatter("%Y-%m-%d", tz=dt.timezone.utc))
        ax.xaxis.set_gid(f"{name}-dates")
        ax.tick_params(axis="x", labelrotation=30, labelsize=7)
        ax.set_xlabel("survey date (UTC)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if i == 0 and histories:
            ax.legend(fontsize=7)
        elif marked is not None:  # the trees are named once, in the first plot
            ax.legend(handles=[marked], fontsize=7)
    fig.tight_layout()
    return svg(fig, "histories", "width, height and NDVI of a few trees over the season")


def _draw_lower_bounds(ax, name: str, bounds: Sequence[tuple[int, float]]):
    """Open upward triangles over the values that are lower bounds ("at least this"),
    one artist with its own id (`histories-<trait>-lower-bounds`) and legend entry."""
    (line,) = ax.plot(
        [_utc(t) for t, _ in bounds],
        [v for _, v in bounds],
        linestyle="none",
        marker="^",
        markersize=11,
        markerfacecolor="none",
        markeredgecolor="k",
        label="lower bound",
        gid=f"{name}-lower-bounds",
    )
    return line


def date_window(times_ns: Sequence[int]) -> tuple[dt.datetime, dt.datetime]:
    """The time axis of a season: whole days from the day before its first survey to the
    day after its last, widened by a twentieth of the season each side for a long one.
    One survey (or several on one day) gets three days around its date, not the years
    matplotlib spreads a single date over."""
    first, last = _utc(min(times_ns)), _utc(max(times_ns))
    pad = max(DAY, math.ceil((last - first) / 20 / DAY) * DAY)
    start = first.replace(hour=0, minute=0, second=0, microsecond=0)
    end = last.replace(hour=0, minute=0, second=0, microsecond=0) + DAY
    return start - pad, end + pad


def _utc(ns: int) -> dt.datetime:
    return dt.datetime.fromtimestamp(ns / 1e9, tz=dt.timezone.utc)
