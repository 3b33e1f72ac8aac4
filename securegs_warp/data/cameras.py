"""Cameras, the scene container, camera paths, and reading one image file.

Conventions (DESIGN.md): ``viewmat`` is world-to-camera (4, 4) with OpenCV camera axes (x right,
y down, z forward); ``K`` is (3, 3) in pixels with pixel centres at +0.5; images are float32 in
[0, 1], (H, W, 3), with alpha (H, W, 1).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import DataError

# How far a pose's 3x3 block may be from a rotation: poses arrive as float32, or written to a few
# digits in a JSON file, so they are rotations only to about 1e-6; a scale, shear or reflection
# is off by far more than this.
ROTATION_TOLERANCE = 1e-3


def rotation_problem(rotation) -> str | None:
    """What keeps a (3, 3) matrix from being a rotation (not orthonormal, or a reflection), within
    ROTATION_TOLERANCE; None when it is one."""
    rotation = np.asarray(rotation, dtype=np.float64)
    deviation = float(np.abs(rotation @ rotation.T - np.eye(3)).max())
    if not deviation <= ROTATION_TOLERANCE:
        return f"R R^T differs from the identity by {deviation:.3g}"
    determinant = float(np.linalg.det(rotation))
    if not abs(determinant - 1.0) <= ROTATION_TOLERANCE:
        return f"determinant {determinant:.4g}"
    return None


def _numbers(values) -> str:
    return "[" + ", ".join(f"{float(v):g}" for v in np.ravel(values)) + "]"


def _check_camera(name: str, viewmat: np.ndarray, K: np.ndarray, width: int, height: int) -> None:
    """DataError naming the camera when its pose is not a rigid world-to-camera transform or its
    intrinsics cannot project (projection divides by the depth and scales by fx, fy)."""
    if width < 1 or height < 1:
        raise DataError(f"camera {name!r}: size {width}x{height}; expected at least 1x1 pixels")
    if not np.isfinite(K).all():
        raise DataError(f"camera {name!r}: K has non-finite entries {_numbers(K)}; expected finite numbers")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise DataError(
            f"camera {name!r}: K has fx={K[0, 0]:g}, fy={K[1, 1]:g}; expected positive focal lengths in pixels"
        )
    problem = rigid_transform_problem(viewmat, "viewmat")
    if problem is not None:
        raise DataError(f"camera {name!r}: {problem}")


def rigid_transform_problem(matrix: np.ndarray, what: str) -> str | None:
    """Why the (4, 4) ``matrix`` (called ``what`` in the sentence) is not a rigid transform: finite,
    bottom row [0, 0, 0, 1], a rotation block within ROTATION_TOLERANCE. None when it is one."""
    if not np.isfinite(matrix).all():
        return f"{what} has non-finite entries {_numbers(matrix)}; expected finite numbers"
    if not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=ROTATION_TOLERANCE):
        return f"{what} bottom row is {_numbers(matrix[3])}; expected [0, 0, 0, 1]"
    problem = rotation_problem(matrix[:3, :3])
    if problem is not None:
        return (f"{what}'s 3x3 block is not a rotation ({problem}); expected an orthonormal matrix with "
                f"determinant 1 within {ROTATION_TOLERANCE:g}")
    return None


def _optional_image(value, height: int, width: int, channels: int, what: str, camera: str):
    """value as a float32 (height, width, channels) array, or None; a wrong shape is a DataError."""
    if value is None:
        return None
    array = np.asarray(value, dtype=np.float32)
    if array.shape != (height, width, channels):
        raise DataError(
            f"camera {camera!r}: {what} has shape {array.shape}, expected ({height}, {width}, {channels}) "
            f"from the camera's {width}x{height} size"
        )
    return array


@dataclass
class Camera:
    """One view: pose, intrinsics and the images seen from it.

    viewmat: (4, 4) float32 world-to-camera, OpenCV axes. K: (3, 3) float32 intrinsics.
    image: (H, W, 3) float32 in [0, 1] or None. alpha: (H, W, 1) float32 or None.
    hidden: (H, W, 3) float32 hidden-view image seen from the same pose, or None.
    hidden_alpha: (H, W, 1) float32 or None.
    """

    name: str
    viewmat: np.ndarray
    K: np.ndarray
    width: int
    height: int
    image: np.ndarray | None = None
    alpha: np.ndarray | None = None
    hidden: np.ndarray | None = None
    hidden_alpha: np.ndarray | None = None

    def __post_init__(self):
        self.viewmat = np.asarray(self.viewmat, dtype=np.float32)
        self.K = np.asarray(self.K, dtype=np.float32)
        if self.viewmat.shape != (4, 4) or self.K.shape != (3, 3):
            raise DataError(
                f"camera {self.name!r}: viewmat must be 4x4 and K 3x3, got {self.viewmat.shape}, {self.K.shape}"
            )
        self.width, self.height = int(self.width), int(self.height)
        _check_camera(self.name, self.viewmat, self.K, self.width, self.height)
        h, w = self.height, self.width
        self.image = _optional_image(self.image, h, w, 3, "image", self.name)
        self.alpha = _optional_image(self.alpha, h, w, 1, "alpha", self.name)
        self.hidden = _optional_image(self.hidden, h, w, 3, "hidden image", self.name)
        self.hidden_alpha = _optional_image(self.hidden_alpha, h, w, 1, "hidden alpha", self.name)

    @property
    def center(self) -> np.ndarray:
        """(3,) camera position in world coordinates: -Rᵀt of the viewmat."""
        rotation, translation = self.viewmat[:3, :3].astype(np.float64), self.viewmat[:3, 3].astype(np.float64)
        return (-rotation.T @ translation).astype(np.float32)

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates [P, 2] and depths [P] (camera z) of world points [P, 3], in float64.
        A point at or behind the camera (depth <= 0) has no meaningful pixel: check the depth."""
        viewmat, K = self.viewmat.astype(np.float64), self.K.astype(np.float64)
        p = np.asarray(points, dtype=np.float64) @ viewmat[:3, :3].T + viewmat[:3, 3]
        depth = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([K[0, 0] * p[:, 0] / depth + K[0, 2], K[1, 1] * p[:, 1] / depth + K[1, 2]], axis=1)
        return uv, depth

    def to_record(self) -> dict:
        """The camera without its images, as JSON-able values (a key stores the cameras it reveals with)."""
        return {"name": self.name, "viewmat": self.viewmat.reshape(-1).tolist(), "K": self.K.reshape(-1).tolist(),
                "width": self.width, "height": self.height}

    @classmethod
    def from_record(cls, record: dict) -> "Camera":
        """Inverse of :meth:`to_record`; a damaged record raises DataError naming what is wrong."""
        try:
            cam = cls(str(record["name"]), np.reshape(record["viewmat"], (4, 4)), np.reshape(record["K"], (3, 3)),
                      int(record["width"]), int(record["height"]))
        except (KeyError, TypeError, ValueError) as e:
            raise DataError(f"camera record {str(record)[:80]!r} is damaged ({e})") from None
        if cam.width < 1 or cam.height < 1 or not (np.isfinite(cam.viewmat).all() and np.isfinite(cam.K).all()):
            raise DataError(f"camera {cam.name!r}: non-positive size or non-finite matrices")
        return cam


@dataclass
class SceneData:
    """A scene ready for training: cameras with their images, and a sparse point cloud.

    points: (N, 3) float32 sparse points (COLMAP's, or a stand-in); colors: (N, 3) float32 in [0, 1].
    background: (3,) float32 colour that the images show where no geometry is (None when unknown,
    e.g. real photographs).
    hidden_kind: None (nothing hidden), "object" (one 3-D object; also views read from a folder of
    hidden images) or "scene" (a whole second scene), with its views in each Camera's
    `hidden`/`hidden_alpha`. hidden_level, for objects only: "object" (the object alone, composited
    over hidden_background, alpha in hidden_alpha) or "scene" (the object inside the scene).
    hidden_bbox: (2, 3) min and max corner of the hidden geometry in world space;
    hidden_points: (M, 3) float32 points on the hidden geometry's surface, for security metrics.
    Both are known only for generated scenes (None for real data).
    """

    name: str
    train: list[Camera]
    test: list[Camera]
    points: np.ndarray
    colors: np.ndarray
    background: np.ndarray | None = None
    hidden_kind: str | None = None
    hidden_level: str | None = None
    hidden_name: str | None = None
    hidden_background: np.ndarray | None = None
    hidden_bbox: np.ndarray | None = None
    hidden_points: np.ndarray | None = None

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=np.float32).reshape(-1, 3)
        self.colors = np.asarray(self.colors, dtype=np.float32).reshape(-1, 3)
        if len(self.points) != len(self.colors):
            raise DataError(f"scene {self.name!r}: {len(self.points)} points but {len(self.colors)} colours")
        for attr in ("background", "hidden_background", "hidden_bbox", "hidden_points"):
            value = getattr(self, attr)
            if value is not None:
                setattr(self, attr, np.asarray(value, dtype=np.float32))

    @property
    def cameras(self) -> list[Camera]:
        """Training then test cameras."""
        return self.train + self.test

    @property
    def evaluation_views(self) -> list[Camera]:
        """The held-out views, or the training views where the scene holds none out
        (``evaluation_split`` says which: metrics of training views are no held-out figures)."""
        return self.test or self.train

    def camera_index(self, cam: Camera) -> int | None:
        """A training view's index, the row of the appearance embedding it trained with (as
        Scaffold-GS's camera uid); None for a held-out view, which renders with row 0."""
        return next((i for i, c in enumerate(self.train) if c is cam), None)

    @property
    def evaluation_split(self) -> str:
        """"test" or "train": the views ``evaluation_views`` gives."""
        return "test" if self.test else "train"

    @property
    def cameras_extent(self) -> float:
        """Radius of the training cameras around their mean centre, times 1.1 (3DGS's scene scale,
        which sets learning rates and densification thresholds)."""
        centers = np.stack([c.center for c in self.train]).astype(np.float64)
        return 1.1 * float(np.linalg.norm(centers - centers.mean(0), axis=1).max())


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(4, 4) float32 world-to-camera viewmat of a camera at `eye` looking at `target` (OpenCV axes:
    image x to the right, y down, i.e. against `up`)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    forward = target - eye
    right = np.cross(forward, up)
    if np.linalg.norm(forward) < 1e-12 or np.linalg.norm(right) < 1e-9 * np.linalg.norm(forward):
        raise ValueError(f"look_at: eye {eye} and target {target} coincide or look along up {up}")
    forward /= np.linalg.norm(forward)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    viewmat = np.eye(4)
    viewmat[:3, :3] = np.stack([right, down, forward])
    viewmat[:3, 3] = -viewmat[:3, :3] @ eye
    return viewmat.astype(np.float32)


def intrinsics_from_fov(fov_x_degrees: float, width: int, height: int) -> np.ndarray:
    """(3, 3) float32 K with square pixels, the principal point at the image centre and the given
    horizontal field of view."""
    focal = 0.5 * width / math.tan(0.5 * math.radians(fov_x_degrees))
    return np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]], dtype=np.float32)


def orbit_positions(n: int, radius: float, height: float, target=(0.0, 0.0, 0.0), phase: float = 0.0) -> np.ndarray:
    """(n, 3) camera positions evenly spaced on a horizontal circle of `radius` around `target`,
    `height` above it (z up), starting at azimuth `phase` radians."""
    azimuth = phase + 2.0 * np.pi * np.arange(n) / n
    offsets = np.stack([radius * np.cos(azimuth), radius * np.sin(azimuth), np.full(n, height)], axis=1)
    return (np.asarray(target, dtype=np.float64) + offsets).astype(np.float32)


def hemisphere_positions(
    n: int, radius: float, target=(0.0, 0.0, 0.0), elevation_degrees=(10.0, 60.0), phase: float = 0.0
) -> np.ndarray:
    """(n, 3) camera positions spread evenly over a band of the upper hemisphere of `radius`
    around `target` (z up): a golden-angle spiral, equal area per camera, from the lowest
    elevation to the highest."""
    low, high = (math.sin(math.radians(e)) for e in elevation_degrees)
    z = low + (high - low) * (np.arange(n) + 0.5) / n
    azimuth = phase + np.pi * (3.0 - math.sqrt(5.0)) * np.arange(n)
    ring = np.sqrt(1.0 - z**2)
    offsets = radius * np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], axis=1)
    return (np.asarray(target, dtype=np.float64) + offsets).astype(np.float32)


def cameras_looking_at(eyes: np.ndarray, target, K: np.ndarray, width: int, height: int, prefix: str) -> list[Camera]:
    """One image-less Camera per row of eyes (n, 3), each looking at target (z up), named
    ``{prefix}_{index:03d}``."""
    return [Camera(f"{prefix}_{k:03d}", look_at(eye, target), K, width, height) for k, eye in enumerate(eyes)]


def read_image(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read an image file as float32 RGB (H, W, 3) in [0, 1] and alpha (H, W, 1) or None.

    8- and 16-bit, grey or colour, with or without alpha. Raises DataError naming the file when it
    is missing or cannot be decoded.
    """
    import imageio.v3 as iio

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: image file not found")
    try:
        raw = iio.imread(path)
        if raw.ndim == 3 and raw.shape[2] == 3 and _keyed_transparency(path):
            raw = iio.imread(path, mode="RGBA")
    except Exception as error:  # imageio raises many types for undecodable files; report them all alike
        # imageio appends plugin install hints on further lines: the first line names the problem.
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise DataError(f"{path}: cannot read image ({reason})") from None
    scale = float(np.iinfo(raw.dtype).max) if np.issubdtype(raw.dtype, np.integer) else 1.0
    pixels = raw.astype(np.float32) / scale
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if pixels.ndim != 3 or pixels.shape[2] not in (1, 2, 3, 4):
        raise DataError(f"{path}: unsupported image layout {raw.shape}")
    pixels = np.clip(pixels, 0.0, 1.0)
    channels = pixels.shape[2]
    colour = pixels[..., :3] if channels >= 3 else np.repeat(pixels[..., :1], 3, axis=2)
    return colour, pixels[..., channels - 1 :] if channels in (2, 4) else None


def _keyed_transparency(path: Path) -> bool:
    """Whether an image keeps its transparency outside an alpha channel (a palette's transparent
    entries, a PNG's transparent colour: size-optimised PNGs do), which a plain read drops."""
    from PIL import Image

    with Image.open(path) as image:
        return "transparency" in image.info


def resize_image(pixels: np.ndarray | None, size: tuple[int, int]) -> np.ndarray | None:
    """(H, W, C) float32 image resized to size = (width, height) by box filtering (area averaging,
    the right filter to shrink photographs); None stays None."""
    from PIL import Image

    if pixels is None or (pixels.shape[1], pixels.shape[0]) == tuple(size):
        return pixels
    # PIL resizes float images one channel at a time (mode "F").
    planes = [Image.fromarray(np.ascontiguousarray(plane)) for plane in pixels.transpose(2, 0, 1)]
    return np.stack([np.asarray(plane.resize(size, Image.BOX)) for plane in planes], axis=-1)


def resize_view(rgb: np.ndarray, alpha: np.ndarray | None,
                size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray | None]:
    """An image's colour (H, W, 3) and alpha (H, W, 1) or None resized to size = (width, height).
    The colour is averaged weighted by alpha (premultiplied, then divided back): a transparent
    pixel's colour, often black, must not bleed into the object's edge, which compositing over a
    background after the resize would show as a dark rim. ``composite`` of the result equals the
    resize of the full-size composite."""
    if alpha is None:
        return resize_image(rgb, size), None
    shrunk_alpha = resize_image(alpha, size)
    premultiplied = resize_image(rgb * alpha, size)
    rgb = np.where(shrunk_alpha > 0, premultiplied / np.maximum(shrunk_alpha, 1e-12), 0.0).astype(np.float32)
    return rgb, shrunk_alpha


def composite(rgb: np.ndarray, alpha: np.ndarray, background) -> np.ndarray:
    """rgb (H, W, 3) over a constant background (3,) with alpha (H, W, 1): rgb*a + bg*(1 - a)."""
    return rgb * alpha + np.asarray(background, dtype=np.float32) * (1.0 - alpha)
