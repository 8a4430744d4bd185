"""Exports of clouds and maps: PLY bytes and a top-down BGR picture. Pure: writing files is the
caller's job (``Path.write_bytes``, ``cv2.imwrite``)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omnid.core.occupancy import CellState, rig_to_robot
from omnid.core.types import PointClass, PointCloud

if TYPE_CHECKING:
    from omnid.core.freespace import FreeSpaceMap

#: RGB of each point class in exports: floor green, obstacle red, drop-off orange.
CLASS_RGB: dict[int, tuple[int, int, int]] = {
    PointClass.FLOOR: (40, 200, 60),
    PointClass.OBSTACLE: (230, 40, 40),
    PointClass.DROPOFF: (255, 150, 0),
}
#: BGR of each cell state in the top-down picture.
CELL_BGR: dict[int, tuple[int, int, int]] = {
    CellState.UNKNOWN: (110, 110, 110),
    CellState.FREE: (225, 240, 225),
    CellState.OBSTACLE: (50, 50, 200),
    CellState.DROPOFF: (0, 140, 255),
}


def _class_rgb(classes: NDArray[np.uint8]) -> NDArray[np.uint8]:
    table = np.zeros((256, 3), dtype=np.uint8)
    table[:] = (200, 200, 200)
    for k, rgb in CLASS_RGB.items():
        table[int(k)] = rgb
    return table[classes]


def ply_bytes(cloud: PointCloud, binary: bool = False) -> bytes:
    """The cloud as a PLY file: vertices with x, y, z (mm, rig frame of SPEC §2), the class code
    (uint8: 0 floor, 1 obstacle, 2 drop-off) and its colour (red, green, blue)."""
    n = len(cloud)
    header = "\n".join(
        [
            "ply",
            f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
            "comment omnid point cloud, mm, rig frame (X forward, Y right, Z down)",
            f"comment floor_depth_mm {cloud.floor_depth_mm:g}",
            f"element vertex {n}",
            "property float x",
            "property float y",
            "property float z",
            "property uchar class",
            "property uchar red",
            "property uchar green",
            "property uchar blue",
            "end_header",
            "",
        ]
    ).encode("ascii")
    rgb = _class_rgb(cloud.classes)
    if binary:
        rec = np.zeros(
            n,
            dtype=[
                ("x", "<f4"),
                ("y", "<f4"),
                ("z", "<f4"),
                ("class", "u1"),
                ("red", "u1"),
                ("green", "u1"),
                ("blue", "u1"),
            ],
        )
        rec["x"], rec["y"], rec["z"] = cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]
        rec["class"] = cloud.classes
        rec["red"], rec["green"], rec["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
        return header + rec.tobytes()
    lines = [
        f"{p[0]:.3f} {p[1]:.3f} {p[2]:.3f} {int(c)} {int(col[0])} {int(col[1])} {int(col[2])}"
        for p, c, col in zip(cloud.xyz, cloud.classes, rgb, strict=True)
    ]
    return header + "".join(line + "\n" for line in lines).encode("ascii")


def parse_ply(data: bytes) -> NDArray[np.void]:
    """Read back what :func:`ply_bytes` writes: a structured array (x, y, z, class, r, g, b)."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    head = data[:end].decode("ascii").splitlines()
    n = next(int(line.split()[2]) for line in head if line.startswith("element vertex"))
    dtype = np.dtype(
        [
            ("x", "<f4"),
            ("y", "<f4"),
            ("z", "<f4"),
            ("class", "u1"),
            ("red", "u1"),
            ("green", "u1"),
            ("blue", "u1"),
        ]
    )
    if any("binary_little_endian" in line for line in head):
        return np.frombuffer(data[end:], dtype=dtype, count=n)
    rows = [line.split() for line in data[end:].decode("ascii").splitlines() if line.strip()]
    out = np.zeros(n, dtype=dtype)
    for k, name in enumerate(dtype.names or ()):
        out[name] = [r[k] for r in rows]
    return out


def render_topdown(
    fmap: FreeSpaceMap,
    cloud: PointCloud | None = None,
    path_xy: ArrayLike | None = None,
    rig_x_offset_mm: float = 0.0,
    cell_px: int = 4,
    footprint_mm: tuple[float, float, float] = (-300.0, 800.0, 350.0),
) -> NDArray[np.uint8]:
    """A BGR picture of the map seen from above, forward up, the chair's left on the left.

    Cells are coloured by state (free light, obstacle red, drop-off orange, unknown gray); the
    cloud's points (rig frame, placed with ``rig_x_offset_mm``) are drawn over it by class; a path
    (robot-frame (N, 2) mm) as a blue line; the chair footprint (x from ``footprint_mm[0]`` to
    ``[1]``, half-width ``[2]``, mm) as a black outline with the axle midpoint; and a 1 m scale bar.
    """
    import cv2

    g = fmap.grid
    s = g.settings
    res = s.resolution_mm
    # Image row grows as x falls, column grows as y falls (left of the chair on the left).
    lut = np.zeros((256, 3), dtype=np.uint8)
    for k, bgr in CELL_BGR.items():
        lut[int(k)] = bgr
    img = lut[np.flip(g.states.view(np.uint8), axis=(0, 1))]
    img = np.ascontiguousarray(np.repeat(np.repeat(img, cell_px, axis=0), cell_px, axis=1))
    px_per_mm = cell_px / res

    def to_px(xy: NDArray[np.float64]) -> NDArray[np.int32]:
        col = (s.y_max_mm - xy[:, 1]) * px_per_mm
        row = (s.x_max_mm - xy[:, 0]) * px_per_mm
        return np.rint(np.column_stack([col, row])).astype(np.int32)

    fx0, fx1, fw = footprint_mm
    foot = np.array([[fx0, -fw], [fx1, -fw], [fx1, fw], [fx0, fw]], dtype=np.float64)
    cv2.polylines(img, [to_px(foot)], True, (0, 0, 0), 2)
    cv2.circle(img, tuple(int(v) for v in to_px(np.zeros((1, 2)))[0]), 3, (0, 0, 0), -1)
    if path_xy is not None:
        path = np.asarray(path_xy, dtype=np.float64).reshape(-1, 2)
        if len(path) >= 2:
            cv2.polylines(img, [to_px(path)], False, (200, 80, 0), 2)
    if cloud is not None and len(cloud):
        pts = to_px(rig_to_robot(cloud.xyz, rig_x_offset_mm))
        rgb = _class_rgb(cloud.classes)
        for (c, r), col in zip(pts, rgb, strict=True):
            bgr = (int(col[2]), int(col[1]), int(col[0]))
            radius = max(1, cell_px // 2)
            # A dark rim keeps a dot visible over a cell of its own colour (drop-off on drop-off).
            cv2.circle(img, (int(c), int(r)), radius + 1, (30, 30, 30), -1)
            cv2.circle(img, (int(c), int(r)), radius, bgr, -1)
    # Scale bar: 1 m, bottom left.
    h_img = img.shape[0]
    bar = math.floor(1000.0 * px_per_mm)
    y0 = h_img - 12
    cv2.line(img, (10, y0), (10 + bar, y0), (0, 0, 0), 3)
    cv2.putText(img, "1 m", (10, y0 - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    return img


def with_legend(
    img: NDArray[np.uint8], title: str, cloud: bool = True, path: bool = False
) -> NDArray[np.uint8]:
    """``img`` (a :func:`render_topdown` picture) under a white band with ``title`` and a legend
    of what the colours mean: cell states, point classes (``cloud``), the path (``path``), the
    chair and the scale. Returns a new BGR image, as wide as ``img`` (at least 560 px)."""
    import cv2

    width = max(img.shape[1], 560)
    items: list[tuple[str, tuple[int, int, int], str]] = [
        ("free", CELL_BGR[CellState.FREE], "cell"),
        ("obstacle", CELL_BGR[CellState.OBSTACLE], "cell"),
        ("drop-off", CELL_BGR[CellState.DROPOFF], "cell"),
        ("unknown", CELL_BGR[CellState.UNKNOWN], "cell"),
    ]
    if cloud:
        for k, label in (
            (PointClass.FLOOR, "floor dot"),
            (PointClass.OBSTACLE, "obstacle dot"),
            (PointClass.DROPOFF, "drop-off dot"),
        ):
            r, g, b = CLASS_RGB[k]
            items.append((label, (b, g, r), "dot"))
    if path:
        items.append(("path", (200, 80, 0), "line"))
    items.append(("chair (axle dot)", (0, 0, 0), "box"))
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.42
    x, y, row_h = 10, 44, 20
    layout: list[tuple[int, int, str, tuple[int, int, int], str]] = []
    for label, colour, kind in items:
        w = 22 + cv2.getTextSize(label, font, scale, 1)[0][0] + 16
        if x + w > width - 10:
            x, y = 10, y + row_h
        layout.append((x, y, label, colour, kind))
        x += w
    band = np.full((y + 14, width, 3), 255, dtype=np.uint8)
    cv2.putText(band, title, (10, 22), font, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    for x0, y0, label, colour, kind in layout:
        if kind == "cell":
            cv2.rectangle(band, (x0, y0 - 10), (x0 + 14, y0 + 2), colour, -1)
            cv2.rectangle(band, (x0, y0 - 10), (x0 + 14, y0 + 2), (90, 90, 90), 1)
        elif kind == "dot":
            cv2.circle(band, (x0 + 7, y0 - 4), 5, (30, 30, 30), -1)
            cv2.circle(band, (x0 + 7, y0 - 4), 4, colour, -1)
        elif kind == "line":
            cv2.line(band, (x0, y0 - 4), (x0 + 14, y0 - 4), colour, 2)
        else:
            cv2.rectangle(band, (x0, y0 - 10), (x0 + 14, y0 + 2), colour, 1)
            cv2.circle(band, (x0 + 7, y0 - 1), 2, colour, -1)
        cv2.putText(band, label, (x0 + 20, y0), font, scale, (0, 0, 0), 1, cv2.LINE_AA)
    body = np.full((img.shape[0], width, 3), 255, dtype=np.uint8)
    body[:, : img.shape[1]] = img
    return np.vstack([band, body])
