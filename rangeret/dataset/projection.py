"""Spherical projection of a LiDAR scan into a range image, and back to the points.

The convention is the one the published checkpoints were trained with (RangeNet++'s):
yaw = -atan2(y, x), pitch = asin(z / |p|), u = floor(0.5 (yaw / pi + 1) W),
v = floor((1 - (pitch + |fov_down|) / fov) H), both clamped into the image, computed in float32.
Sensors that give each point its laser take the row from that number instead: `row="laser_id"`
(PandaSet's Pandar64, laser 0 the top beam) makes v the point's fifth value as an integer, and
`row="ring"` (Velodyne's numbering, ring 0 the lowest beam, as in nuScenes) makes v = H - 1 - ring,
so row 0 is the top beam either way; the number must give a row of the image.
Where several points fall on one pixel the closest wins (equal depths: the lower point index).
Each point keeps its (u, v), so per-pixel predictions go back to every point losslessly.
"""

from __future__ import annotations

import threading
from dataclasses import asdict, dataclass

import numpy as np

from rangeret.exceptions import InputError

#: Normalisation of the five input channels (range, x, y, z, remission) on SemanticKITTI.
CHANNEL_MEANS = (12.12, 10.88, 0.23, -1.04, 0.21)
CHANNEL_STDS = (12.32, 11.47, 6.91, 0.86, 0.16)

#: Where a point's row comes from: its pitch, or the fifth value of its record, a laser id counted
#: from the top beam (`laser_id`) or a ring counted from the lowest beam (`ring`).
ROW_SOURCES = ("pitch", "laser_id", "ring")
#: The row sources that read the fifth value of a point's record.
BEAM_ROWS = ("laser_id", "ring")


#: The largest range image: rows and columns (real sensors have at most 256 beams and a few
#: thousand columns; a larger image only takes memory without bound).
MAX_HEIGHT = 512
MAX_WIDTH = 8192


class ProjectionError(InputError, ValueError):
    """A projection that cannot be made: settings out of range, or points that do not fit it."""


@dataclass(frozen=True)
class ProjectionConfig:
    """Resolution, vertical field of view (degrees), channel normalisation and row source of a
    range image."""

    height: int = 64
    width: int = 1024
    fov_up: float = 3.0
    fov_down: float = -25.0
    means: tuple[float, ...] = CHANNEL_MEANS
    stds: tuple[float, ...] = CHANNEL_STDS
    row: str = "pitch"

    def __post_init__(self) -> None:
        if self.height < 1 or self.width < 1:
            raise ProjectionError(f"image size must be positive, got {self.height} x {self.width}")
        if self.height > MAX_HEIGHT or self.width > MAX_WIDTH:
            raise ProjectionError(
                f"image size must be at most {MAX_HEIGHT} x {MAX_WIDTH}, got {self.height} x "
                f"{self.width}"
            )
        if abs(self.fov_up) + abs(self.fov_down) <= 0:
            raise ProjectionError("the vertical field of view is empty (fov_up and fov_down are 0)")
        if len(self.means) != 5 or len(self.stds) != 5:
            raise ProjectionError("means and stds need one value per channel (5)")
        if any(not s > 0 for s in self.stds):
            raise ProjectionError(f"stds must be positive, got {list(self.stds)}")
        if self.row not in ROW_SOURCES:
            raise ProjectionError(f"row must be one of {', '.join(ROW_SOURCES)}, got {self.row!r}")

    def to_dict(self) -> dict:
        """Plain-data form, for checkpoints and reports."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


@dataclass
class Projection:
    """A scan projected into a range image, with each point's pixel.

    image: (5, H, W) float32 normalised (range, x, y, z, remission), 0 on empty pixels.
    mask: (H, W) bool, True where a point landed.
    proj_range: (H, W) float32 range of the winning point, -1 where empty.
    proj_idx: (H, W) int64 index of the winning point, -1 where empty.
    proj_x, proj_y: (N,) int64 column and row of every point, -1 for points not projected.
    unproj_range: (N,) float32 range of every point (0 for points not projected).
    """

    image: np.ndarray
    mask: np.ndarray
    proj_range: np.ndarray
    proj_idx: np.ndarray
    proj_x: np.ndarray
    proj_y: np.ndarray
    unproj_range: np.ndarray

    def __post_init__(self) -> None:
        height, width = check_pixels(self.proj_range, self.unproj_range, self.proj_x, self.proj_y)
        for name in ("mask", "proj_idx"):
            if getattr(self, name).shape != (height, width):
                raise ValueError(f"{name} must have the shape of proj_range, ({height}, {width})")
        if self.image.ndim != 3 or self.image.shape[1:] != (height, width):
            raise ValueError(f"image must be (C, {height}, {width}), got {self.image.shape}")

    @property
    def num_points(self) -> int:
        """Number of points of the scan, projected or not."""
        return int(self.proj_x.shape[0])

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool, True for points that have a pixel."""
        return self.proj_x >= 0

    def to_points(self, pixel_values: np.ndarray, fill: int | float = 0) -> np.ndarray:
        """Per-point values read from an (H, W) per-pixel map; points without a pixel get `fill`."""
        pixel_values = np.asarray(pixel_values)
        out = np.full(self.num_points, fill, dtype=pixel_values.dtype)
        valid = self.valid
        out[valid] = pixel_values[self.proj_y[valid], self.proj_x[valid]]
        return out

    def to_image(self, point_values: np.ndarray, fill: int | float = 0) -> np.ndarray:
        """(H, W) map of per-point values taken from each pixel's winning point; `fill` elsewhere."""
        point_values = np.asarray(point_values)
        out = np.full(self.mask.shape, fill, dtype=point_values.dtype)
        out[self.mask] = point_values[self.proj_idx[self.mask]]
        return out


def check_pixels(
    proj_range: np.ndarray, unproj_range: np.ndarray, proj_x: np.ndarray, proj_y: np.ndarray
) -> tuple[int, int]:
    """The image's (H, W), once the arrays are seen to describe one scan's pixels as `Projection`
    holds them; otherwise a ProjectionError naming the array (what per-point labelling relies on)."""
    for name, value, integer in (
        ("proj_range", proj_range, False),
        ("unproj_range", unproj_range, False),
        ("proj_x", proj_x, True),
        ("proj_y", proj_y, True),
    ):
        kind = value.dtype.kind
        if kind not in "fiu":
            raise ProjectionError(f"{name} must hold real numbers, got dtype {value.dtype}")
        if integer and kind == "f":
            raise ProjectionError(f"{name} must hold integers, got dtype {value.dtype}")
    if proj_range.ndim != 2:
        raise ProjectionError(f"proj_range must be (H, W), got shape {proj_range.shape}")
    for name, value in (("unproj_range", unproj_range), ("proj_x", proj_x), ("proj_y", proj_y)):
        if value.ndim != 1:
            raise ProjectionError(f"{name} must be (N,), got shape {value.shape}")
    if not unproj_range.shape == proj_x.shape == proj_y.shape:
        raise ProjectionError(
            "unproj_range, proj_x and proj_y must have the same shape (N,), got "
            f"{unproj_range.shape}, {proj_x.shape} and {proj_y.shape}"
        )
    height, width = proj_range.shape
    if proj_x.size:
        low, high = int(proj_x.min()), int(proj_x.max())
        if low < -1:
            raise ProjectionError("proj_x must be -1 (not projected) or a column in [0, W)")
        if high >= width:
            raise ProjectionError(f"proj_x must be below the image width {width}, got {high}")
        rows = proj_y if low >= 0 else proj_y[proj_x >= 0]
        if rows.size and (int(rows.min()) < 0 or int(rows.max()) >= height):
            raise ProjectionError(
                f"proj_y must be in [0, {height}) for projected points, "
                f"got values in [{int(rows.min())}, {int(rows.max())}]"
            )
    return height, width


def _laser_rows(lasers: np.ndarray, idx: np.ndarray, height: int, row: str) -> np.ndarray:
    """Rows of the projected points `idx` from their laser ids (`row="laser_id"`) or rings
    (`row="ring"`, counted from the bottom); ProjectionError for a number off the image."""
    rows = lasers[idx].astype(np.int32).astype(np.int64)
    if row == "ring":
        rows = height - 1 - rows
    bad = np.flatnonzero((rows < 0) | (rows >= height))
    if bad.size:
        first = int(idx[bad[0]])
        name = "laser id" if row == "laser_id" else "ring"
        raise ProjectionError(
            f"{bad.size} point(s) have a {name} outside the image's rows 0..{height - 1}, "
            f"the first at point index {first} ({name} {lasers[first]:g})"
        )
    return rows


def project(
    points: np.ndarray,
    height: int = 64,
    width: int = 1024,
    fov_up: float = 3.0,
    fov_down: float = -25.0,
    means: tuple[float, ...] = CHANNEL_MEANS,
    stds: tuple[float, ...] = CHANNEL_STDS,
) -> Projection:
    """Project (N, 4) points (x, y, z, remission) into a (5, H, W) normalised range image.

    Points at the origin or with non-finite coordinates get no pixel (proj_x = proj_y = -1).
    """
    config = ProjectionConfig(height, width, fov_up, fov_down, tuple(means), tuple(stds))
    return project_with(points, config)


def project_with(points: np.ndarray, config: ProjectionConfig) -> Projection:
    """`project` with its parameters gathered in a `ProjectionConfig`.

    With `row="laser_id"` or `row="ring"` the points are (N, 5) and a number outside the image's
    rows (for a projected point) is a ValueError naming the first such point.
    """
    pts = np.asarray(points)
    columns = 5 if config.row in BEAM_ROWS else 4
    if pts.ndim != 2 or pts.shape[1] < columns:
        raise ProjectionError(f"points must have shape (N, {columns}), got {pts.shape}")
    lasers = pts[:, 4] if config.row in BEAM_ROWS else None
    h, w = config.height, config.width
    n = pts.shape[0]
    work = _Scratch(n, h * w)

    # Channel-major copy: contiguous columns make every later gather and ufunc cheaper.
    cols = work.take("cols", (4, n), np.float32)
    np.copyto(cols, pts[:, :4].T, casting="unsafe")
    # The depth as `point_ranges` computes it: sqrt((x x + y y) + z z) in float32.
    depth = work.take("depth", n, np.float32)
    square = work.take("square", n, np.float32)
    with np.errstate(invalid="ignore", over="ignore"):
        np.multiply(cols[0], cols[0], out=depth)
        depth += np.multiply(cols[1], cols[1], out=square)
        depth += np.multiply(cols[2], cols[2], out=square)
        np.sqrt(depth, out=depth)
    valid = work.take("valid", n, np.bool_)
    check = work.take("check", n, np.bool_)
    np.isfinite(depth, out=valid)
    valid &= np.greater(depth, 0, out=check)
    valid &= np.isfinite(cols[3], out=check)
    if valid.all():
        idx = None
        d = depth
    else:
        idx = np.flatnonzero(valid)
        cols, d = cols[:, idx], depth[idx]
    x, y, z = cols[0], cols[1], cols[2]
    m = d.size

    fov_up = abs(config.fov_up) / 180.0 * np.pi
    fov_down = abs(config.fov_down) / 180.0 * np.pi
    fov = np.float32(fov_down + fov_up)
    # u = floor(0.5 (yaw / pi + 1) W), yaw = -atan2(y, x); v = floor((1 - (pitch + fov_down) /
    # fov) H), pitch = asin(clip(z / depth)): each step in float32, in place.
    u = np.arctan2(y, x, out=work.take("u", m, np.float32))
    np.negative(u, out=u)
    u /= np.float32(np.pi)
    u += np.float32(1.0)
    u *= np.float32(0.5)
    u *= np.float32(w)
    v = np.divide(z, d, out=work.take("v", m, np.float32))
    np.clip(v, np.float32(-1), np.float32(1), out=v)
    np.arcsin(v, out=v)
    v += np.float32(fov_down)
    v /= fov
    np.subtract(np.float32(1.0), v, out=v)
    v *= np.float32(h)
    np.clip(np.floor(u, out=u), 0, w - 1, out=u)
    np.clip(np.floor(v, out=v), 0, h - 1, out=v)
    column = work.take("column", m, np.int32)
    np.copyto(column, u, casting="unsafe")
    if lasers is not None:
        row = _laser_rows(lasers, np.arange(n) if idx is None else idx, h, config.row)
    else:
        row = work.take("row", m, np.int32)
        np.copyto(row, v, casting="unsafe")

    # Closest point wins, among equal depths the lower index: two scatter-minimum passes, first
    # over depths, then over the indices of the points that reach their pixel's minimum.
    pixel = np.multiply(row, w, out=work.take("pixel", m, np.int32), casting="unsafe")
    pixel += column
    nearest = work.take("nearest", h * w, np.float32)
    nearest.fill(np.inf)
    np.minimum.at(nearest, pixel, d)
    reached = np.equal(d, np.take(nearest, pixel, out=work.take("reach", m, np.float32)))
    candidates = np.flatnonzero(reached)
    first = work.take("first", h * w, np.int64)
    first.fill(m)
    np.minimum.at(first, np.take(pixel, candidates), candidates)
    win_pixel = np.flatnonzero(first < m)
    winners = np.take(first, win_pixel)

    proj_idx = np.full(h * w, -1, dtype=np.int64)
    proj_idx[win_pixel] = winners if idx is None else np.take(idx, winners)
    proj_range = np.full(h * w, -1.0, dtype=np.float32)
    proj_range[win_pixel] = np.take(d, winners)

    # Each channel normalised as (value - mean) / std in float32 and scattered to its pixels.
    image = np.zeros((5, h * w), dtype=np.float32)
    channel = work.take("channel", winners.size, np.float32)
    for c, values in enumerate((d, x, y, z, cols[3])):
        np.take(values, winners, out=channel)
        channel -= np.float32(config.means[c])
        channel /= np.float32(config.stds[c])
        image[c, win_pixel] = channel

    if idx is None:
        proj_x = column.astype(np.int64)
        proj_y = row.astype(np.int64)
        unproj_range = d.copy()
    else:
        proj_x = np.full(n, -1, dtype=np.int64)
        proj_y = np.full(n, -1, dtype=np.int64)
        proj_x[idx] = column
        proj_y[idx] = row
        unproj_range = np.zeros(n, dtype=np.float32)
        unproj_range[idx] = d

    return Projection(
        image=image.reshape(5, h, w),
        mask=(proj_idx >= 0).reshape(h, w),
        proj_range=proj_range.reshape(h, w),
        proj_idx=proj_idx.reshape(h, w),
        proj_x=proj_x,
        proj_y=proj_y,
        unproj_range=unproj_range,
    )


class _Scratch:
    """A thread's temporaries for one projection, kept between calls: fresh ones would cost a
    page fault per 4 kB touched each time, most of a projection's time. Scans of more than
    `_SCRATCH_POINTS` points or images of more than `_SCRATCH_PIXELS` pixels use fresh arrays."""

    _kept = threading.local()

    def __init__(self, points: int, pixels: int) -> None:
        keep = points <= _SCRATCH_POINTS and pixels <= _SCRATCH_PIXELS
        self.buffers: dict[str, np.ndarray] = (
            self._kept.__dict__.setdefault("buffers", {}) if keep else {}
        )

    def take(self, name: str, shape: int | tuple[int, ...], dtype: type) -> np.ndarray:
        """The buffer `name` as an array of `shape` and `dtype` (contents undefined)."""
        size = int(np.prod(shape))
        buffer = self.buffers.get(name)
        if buffer is None or buffer.dtype != dtype or buffer.size < size:
            buffer = self.buffers[name] = np.empty(size, dtype=dtype)
        return buffer[:size].reshape(shape)


#: The largest scan (about 55 bytes a point) and image (12 bytes a pixel) whose temporaries a
#: thread keeps: about 30 MB at most.
_SCRATCH_POINTS = 1 << 19
_SCRATCH_PIXELS = 1 << 20
