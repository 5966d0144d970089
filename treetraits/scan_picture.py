"""`treetraits inspect --png`: one scan drawn with OpenCV, a top view (x-y, base frame) and
a side view (z against the horizontal axis along which the returns spread most), every
return grey, each object's returns coloured by its verdict, its id beside it, a legend of
the verdicts in the scan and a metric scale bar in each view."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from treetraits.inspection import shown_verdict

if TYPE_CHECKING:
    from treetraits.pipeline.detection import Cluster

WIDTH, HEIGHT = 1200, 800
LEGEND_H = 44
BACKGROUND = (255, 255, 255)
RETURN_GREY = (185, 185, 185)
TEXT = (30, 30, 30)

# BGR. Tree green; what the surface or the camera speaks against red; too low brown;
# too thin orange; too high, too tall or too wide purple.
VERDICT_COLOURS: dict[str, tuple[int, int, int]] = {
    "tree": (40, 170, 0),
    "smooth": (40, 40, 220),
    "not_green": (40, 40, 220),
    "low": (19, 69, 139),
    "thin": (0, 140, 255),
    "slender": (0, 140, 255),
    "floating": (200, 40, 160),
    "tall": (200, 40, 160),
    "wide": (200, 40, 160),
    "undecided": (0, 200, 230),  # yellow: a tree's shape, no evidence either way here
}
OTHER = (120, 120, 120)  # a verdict not listed above


def colour_of(verdict: str) -> tuple[int, int, int]:
    return VERDICT_COLOURS.get(verdict, OTHER)


def side_axis(xyz: np.ndarray) -> int:
    """0 (x) or 1 (y): the horizontal axis along which the returns spread most (5-95th
    percentile span). A level LiDAR sees around it; a sideways one, a vertical slice
    across its travel (y-z)."""
    if len(xyz) == 0:
        return 0
    span = np.percentile(xyz[:, :2], 95, axis=0) - np.percentile(xyz[:, :2], 5, axis=0)
    return int(np.argmax(span))


class _View:
    """A metric window of the plane onto a pixel rectangle, one scale for both axes."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, rect: tuple[int, int, int, int]):
        x0, y0, w, h = rect
        self.rect = rect
        span = np.maximum(hi - lo, 1.0)
        self.scale = min((w - 40) / span[0], (h - 60) / span[1])  # px per m
        centre = (lo + hi) / 2
        self.origin = np.array([x0 + w / 2, y0 + h / 2 - 10])
        self.centre = centre

    def px(self, uv: np.ndarray) -> np.ndarray:
        """N x 2 metric (u right, v up) to N x 2 int pixels."""
        out = np.empty((len(uv), 2))
        out[:, 0] = self.origin[0] + (uv[:, 0] - self.centre[0]) * self.scale
        out[:, 1] = self.origin[1] - (uv[:, 1] - self.centre[1]) * self.scale
        return np.round(out).astype(np.int64)

    def inside(self, p: np.ndarray) -> np.ndarray:
        x0, y0, w, h = self.rect
        return (p[:, 0] >= x0) & (p[:, 0] < x0 + w) & (p[:, 1] >= y0) & (p[:, 1] < y0 + h)


def _window(all_uv: np.ndarray, objects_uv: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The metric window: the returns' 1-99th percentiles and every object, 0.5 m margin."""
    parts = []
    if len(all_uv):
        parts += [np.percentile(all_uv, 1, axis=0), np.percentile(all_uv, 99, axis=0)]
    for uv in objects_uv:
        if len(uv):
            parts += [uv.min(axis=0), uv.max(axis=0)]
    if not parts:
        return np.array([-1.0, -1.0]), np.array([1.0, 1.0])
    stacked = np.array(parts)
    return stacked.min(axis=0) - 0.5, stacked.max(axis=0) + 0.5


def _dots(image: np.ndarray, view: _View, uv: np.ndarray, colour, size: int) -> None:
    if not len(uv):
        return
    p = view.px(uv)
    p = p[view.inside(p)]
    for dy in range(size):
        for dx in range(size):
            q = p + np.array([dx - size // 2, dy - size // 2])
            x0, y0, w, h = view.rect
            ok = (q[:, 0] >= x0) & (q[:, 0] < x0 + w) & (q[:, 1] >= y0) & (q[:, 1] < y0 + h)
            image[q[ok, 1], q[ok, 0]] = colour


def _scale_bar(image: np.ndarray, view: _View) -> None:
    import cv2

    x0, y0, w, h = view.rect
    target = (w - 40) / 4 / view.scale  # about a quarter of the panel, in metres
    metres = max(m for m in (0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50) if m <= max(target, 0.1))
    length = round(metres * view.scale)
    left, y = x0 + 20, y0 + h - 18
    cv2.line(image, (left, y), (left + length, y), TEXT, 2)
    for x in (left, left + length):
        cv2.line(image, (x, y - 6), (x, y + 6), TEXT, 2)
    label = f"{metres:g} m"
    cv2.putText(image, label, (left + length + 8, y + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.5, TEXT, 1)


def draw_scan(
    all_xyz: np.ndarray,
    clusters: list[Cluster],
    T_base_lidar: np.ndarray,
    title: str,
    box: tuple[tuple[float, float], ...] | None = None,
) -> np.ndarray:
    """The picture, HEIGHT x WIDTH x 3 uint8 (BGR). `all_xyz`: every return of the scan in
    `base` (N x 3); `box`: (x, y, z) ranges in metres, the returns drawn (the detection's
    crop box: the far ground rings would shrink the objects to dots)."""
    import cv2

    if box is not None:
        inside = np.ones(len(all_xyz), dtype=bool)
        for axis, (lo, hi) in enumerate(box):
            inside &= (all_xyz[:, axis] >= lo) & (all_xyz[:, axis] <= hi)
        all_xyz = all_xyz[inside]

    image = np.full((HEIGHT, WIDTH, 3), BACKGROUND, dtype=np.uint8)
    panel_w, panel_h = WIDTH // 2, HEIGHT - LEGEND_H
    axis = side_axis(
        np.concatenate([np.asarray(c.points) for c in clusters]) if clusters else all_xyz
    )
    lidar = np.asarray(T_base_lidar, dtype=float)[:3, 3]
    views = (
        ("top view (x-y)", (0, 1), (0, LEGEND_H, panel_w, panel_h), "x", "y"),
        (
            f"side view ({'xy'[axis]}-z)",
            (axis, 2),
            (panel_w, LEGEND_H, panel_w, panel_h),
            "xy"[axis],
            "z",
        ),
    )
    for name, (u, v), rect, u_name, v_name in views:
        all_uv = all_xyz[:, [u, v]]
        objects_uv = [np.asarray(c.points)[:, [u, v]] for c in clusters]
        lo, hi = _window(all_uv, objects_uv)
        view = _View(lo, hi, rect)
        _dots(image, view, all_uv, RETURN_GREY, 1)
        for c, uv in zip(clusters, objects_uv, strict=True):
            _dots(image, view, uv, colour_of(shown_verdict(c)), 2)
        # The LiDAR: a black cross.
        lp = view.px(lidar[[u, v]][None])[0]
        cv2.drawMarker(image, (int(lp[0]), int(lp[1])), TEXT, cv2.MARKER_CROSS, 12, 2)
        for i, (c, uv) in enumerate(zip(clusters, objects_uv, strict=True)):
            if not len(uv):
                continue
            anchor = np.array([[uv[:, 0].max(), uv[:, 1].max()]])
            p = view.px(anchor)[0]
            x = int(min(max(p[0] + 3, rect[0] + 2), rect[0] + rect[2] - 30))
            y = int(min(max(p[1] - 3, rect[1] + 14), rect[1] + rect[3] - 4))
            colour = colour_of(shown_verdict(c))
            cv2.putText(image, str(i), (x, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1)
        cv2.putText(
            image,
            f"{name}: {u_name} right, {v_name} up, base frame",
            (rect[0] + 10, rect[1] + 18),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5,
            TEXT,
            1,
        )
        _scale_bar(image, view)
    cv2.line(image, (panel_w, LEGEND_H), (panel_w, HEIGHT), (90, 90, 90), 1)
    cv2.line(image, (0, LEGEND_H), (WIDTH, LEGEND_H), (90, 90, 90), 1)
    _legend(image, clusters, title)
    return image


def _legend(image: np.ndarray, clusters: list[Cluster], title: str) -> None:
    """The verdicts present in this scan with their counts (a verdict not in the scan is
    left out, so its colour appears nowhere in the picture), and the grey of the other
    returns."""
    import cv2

    counts: dict[str, int] = {}
    for c in clusters:
        counts[shown_verdict(c)] = counts.get(shown_verdict(c), 0) + 1
    x, y = 10, 28
    cv2.putText(image, title, (x, y), cv2.FONT_HERSHEY_SIMPLEX, 0.5, TEXT, 1)
    x += 12 + cv2.getTextSize(title, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)[0][0]
    entries = [("other returns", RETURN_GREY)] + [
        (f"{verdict} ({n})", colour_of(verdict)) for verdict, n in sorted(counts.items())
    ]
    for label, colour in entries:
        cv2.rectangle(image, (x, y - 11), (x + 14, y + 3), colour, -1)
        cv2.putText(image, label, (x + 19, y), cv2.FONT_HERSHEY_SIMPLEX, 0.5, TEXT, 1)
        x += 30 + cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)[0][0]
        if x > WIDTH - 60:
            break


def write_png(path, image: np.ndarray) -> None:
    import cv2

    from treetraits.errors import FileAccessError

    ok, data = cv2.imencode(".png", image)
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
        raise FileAccessError(f"{path}: OpenCV could not encode the picture")
    with open(path, "wb") as f:
        f.write(data.tobytes())
