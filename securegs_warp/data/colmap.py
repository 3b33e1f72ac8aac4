"""Reading a COLMAP reconstruction: ``images/`` plus ``sparse/0/`` (binary or text model).

Only undistorted pinhole-like camera models are read: PINHOLE, SIMPLE_PINHOLE and SIMPLE_RADIAL.
SIMPLE_RADIAL's distortion coefficient is ignored (with a warning): fine for the nearly
undistorted images COLMAP's undistorter writes, wrong for raw photographs with strong distortion.
Every `holdout`-th image by sorted name (index % holdout == 0) is a test view, as in 3DGS.
COLMAP's world-to-camera rotation (quaternion w, x, y, z) and translation already use OpenCV
camera axes and pixel centres at +0.5, so they become viewmat and K unchanged.
"""
from __future__ import annotations

import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .cameras import Camera, SceneData, composite, read_image, resize_view
from .errors import DataError

# COLMAP's camera models: id -> (name, number of parameters). All are listed so that a model we
# cannot use is reported by name rather than as a parse error.
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
PARAM_COUNTS = dict(CAMERA_MODELS.values())
SUPPORTED_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL")


@dataclass
class ColmapCamera:
    """One COLMAP camera: model name, size in pixels, and the model's parameters (float64)."""

    id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    """One registered image: world-to-camera rotation qvec (w, x, y, z) and translation tvec."""

    id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str


class _BinaryReader:
    """Little-endian reads from a whole file, each checked against the file's end, so a truncated
    file gives a DataError that says where, not a struct.error."""

    def __init__(self, path: Path):
        self.path = path
        self.data = path.read_bytes()
        self.offset = 0

    def take(self, size: int, what: str) -> bytes:
        end = self.offset + size
        if end > len(self.data):
            raise DataError(
                f"{self.path}: truncated file: {what} needs {size} bytes at byte {self.offset}, "
                f"but the file has only {len(self.data)} bytes"
            )
        chunk = self.data[self.offset : end]
        self.offset = end
        return chunk

    def unpack(self, fmt: str, what: str) -> tuple:
        return struct.unpack("<" + fmt, self.take(struct.calcsize("<" + fmt), what))

    def cstring(self, what: str) -> str:
        end = self.data.find(b"\0", self.offset)
        if end < 0:
            raise DataError(f"{self.path}: truncated file: {what} at byte {self.offset} has no terminating NUL")
        text = self.data[self.offset : end].decode("utf-8", errors="replace")
        self.offset = end + 1
        return text

    def records(self, count: int, least: int, what: str) -> int:
        """``count``, once the bytes left can hold that many records of at least ``least`` bytes
        each: a damaged count must not allocate before the file runs out."""
        if count * least > len(self.data) - self.offset:
            raise DataError(f"{self.path}: truncated or damaged file: {count} {what} need at least "
                            f"{count * least} bytes, but {len(self.data) - self.offset} are left")
        return count

    def finish(self):
        if self.offset != len(self.data):
            raise DataError(f"{self.path}: {len(self.data) - self.offset} unexpected bytes after the last record")


def _model_name(path: Path, camera_id: int, model_id: int) -> str:
    if model_id not in CAMERA_MODELS:
        raise DataError(f"{path}: camera {camera_id} has unknown camera model id {model_id}")
    return CAMERA_MODELS[model_id][0]


def read_cameras_binary(path: Path) -> dict[int, ColmapCamera]:
    """cameras.bin -> {camera id: ColmapCamera}."""
    reader = _BinaryReader(path)
    cameras = {}
    for k in range(reader.unpack("Q", "the camera count")[0]):
        camera_id, model_id, width, height = reader.unpack("iiQQ", f"camera record {k}")
        model = _model_name(path, camera_id, model_id)
        params = reader.unpack(f"{PARAM_COUNTS[model]}d", f"the {model} parameters of camera {camera_id}")
        cameras[camera_id] = ColmapCamera(camera_id, model, width, height, np.array(params))
    reader.finish()
    return cameras


def read_images_binary(path: Path) -> dict[int, ColmapImage]:
    """images.bin -> {image id: ColmapImage}; the per-image 2-D keypoints are skipped."""
    reader = _BinaryReader(path)
    images = {}
    for k in range(reader.unpack("Q", "the image count")[0]):
        image_id, qw, qx, qy, qz, tx, ty, tz, camera_id = reader.unpack("i7di", f"image record {k}")
        name = reader.cstring(f"the name of image {image_id}")
        (n_points,) = reader.unpack("Q", f"the keypoint count of image {name!r}")
        reader.take(24 * n_points, f"the {n_points} keypoints (x, y, point id) of image {name!r}")
        images[image_id] = ColmapImage(image_id, np.array([qw, qx, qy, qz]), np.array([tx, ty, tz]), camera_id, name)
    reader.finish()
    return images


def read_points3d_binary(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """points3D.bin -> positions (N, 3) float64 and colours (N, 3) uint8; tracks are skipped."""
    reader = _BinaryReader(path)
    # A point record is at least 43 bytes (id, x y z, r g b, error, track length).
    count = reader.records(reader.unpack("Q", "the point count")[0], 43, "points")
    xyz, rgb = np.empty((count, 3)), np.empty((count, 3), dtype=np.uint8)
    for k in range(count):
        values = reader.unpack("Q3d3Bd", f"point record {k}")
        _check_point(f"{path}: point {values[0]} (record {k})", values[1:4])
        xyz[k], rgb[k] = values[1:4], values[4:7]
        (track_length,) = reader.unpack("Q", f"the track length of point {values[0]}")
        reader.take(8 * track_length, f"the {track_length}-element track of point {values[0]}")
    reader.finish()
    return xyz, rgb


def _check_point(where: str, xyz) -> None:
    """A DataError at `where` when a point's coordinates are not all finite: one NaN point would
    spread NaN through the anchors initialised from it."""
    if not np.isfinite(xyz).all():
        raise DataError(f"{where} has non-finite coordinates ({_numbers(xyz)}); expected finite x y z")


def _numbers(values) -> str:
    return ", ".join(f"{float(v):g}" for v in values)


def _text_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, line) of every line that is not a comment."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as error:
        raise DataError(f"{path}: cannot read ({error.strerror})") from None
    return [(no, line) for no, line in enumerate(text.splitlines(), 1) if not line.lstrip().startswith("#")]


def _parse(path: Path, line_no: int, tokens: list[str], types: tuple, what: str) -> list:
    """tokens converted by types (one type per leading token), or a DataError naming the line."""
    if len(tokens) < len(types):
        raise DataError(f"{path}:{line_no}: {what} needs {len(types)} fields, found {len(tokens)}")
    try:
        return [kind(token) for kind, token in zip(types, tokens)]
    except ValueError as error:
        raise DataError(f"{path}:{line_no}: bad {what} ({error})") from None


def read_cameras_text(path: Path) -> dict[int, ColmapCamera]:
    """cameras.txt (CAMERA_ID MODEL WIDTH HEIGHT PARAMS...) -> {camera id: ColmapCamera}."""
    cameras = {}
    for no, line in _text_lines(path):
        tokens = line.split()
        if not tokens:
            continue
        camera_id, model, width, height = _parse(path, no, tokens, (int, str, int, int), "camera line")
        if model not in PARAM_COUNTS:
            raise DataError(f"{path}:{no}: camera {camera_id} has unknown camera model {model!r}")
        count = PARAM_COUNTS[model]
        params = _parse(path, no, tokens[4:], (float,) * count, f"{model} parameter list")
        cameras[camera_id] = ColmapCamera(camera_id, model, width, height, np.array(params))
    return cameras


def read_images_text(path: Path) -> dict[int, ColmapImage]:
    """images.txt (two lines per image: IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then its
    keypoints, possibly an empty line) -> {image id: ColmapImage}."""
    lines = _text_lines(path)
    images = {}
    k = 0
    while k < len(lines):
        no, line = lines[k]
        if not line.strip():
            k += 1
            continue
        fields = _parse(path, no, line.split(), (int,) + (float,) * 7 + (int, str), "image line")
        # The name may contain spaces: it is everything after the ninth field.
        name = line.split(maxsplit=9)[9].strip()
        images[fields[0]] = ColmapImage(fields[0], np.array(fields[1:5]), np.array(fields[5:8]), fields[8], name)
        # The next line lists the image's keypoints (x y point-id triples), which we do not need; a
        # file without it would silently lose every other image.
        if k + 1 < len(lines) and len(lines[k + 1][1].split()) % 3:
            raise DataError(f"{path}:{lines[k + 1][0]}: expected the keypoints of image {name!r} (x y point3D_id "
                            "triples, or an empty line) after its image line; images.txt has two lines per image")
        k += 2
    return images


def read_points3d_text(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """points3D.txt (POINT3D_ID X Y Z R G B ERROR TRACK...) -> positions (N, 3), colours (N, 3) uint8."""
    xyz, rgb = [], []
    for no, line in _text_lines(path):
        tokens = line.split()
        if tokens:
            values = _parse(path, no, tokens, (int, float, float, float, int, int, int, float), "point line")
            _check_point(f"{path}:{no}: point {values[0]}", values[1:4])
            if not all(0 <= c <= 255 for c in values[4:7]):
                raise DataError(f"{path}:{no}: point {values[0]} has colour {values[4:7]}; expected R G B in 0..255")
            xyz.append(values[1:4])
            rgb.append(values[4:7])
    return np.array(xyz, dtype=np.float64).reshape(-1, 3), np.array(rgb, dtype=np.uint8).reshape(-1, 3)


def _model_file(sparse: Path, stem: str) -> Path:
    """sparse/<stem>.bin if present, else sparse/<stem>.txt, else a DataError."""
    for suffix in (".bin", ".txt"):
        if (sparse / (stem + suffix)).is_file():
            return sparse / (stem + suffix)
    raise DataError(f"{sparse}: neither {stem}.bin nor {stem}.txt is there")


def read_model(sparse: Path) -> tuple[dict[int, ColmapCamera], dict[int, ColmapImage], np.ndarray, np.ndarray]:
    """A sparse model folder -> cameras, images, point positions (N, 3), point colours (N, 3) uint8."""
    readers = {
        "cameras": (read_cameras_binary, read_cameras_text),
        "images": (read_images_binary, read_images_text),
        "points3D": (read_points3d_binary, read_points3d_text),
    }
    results = []
    for stem, (binary, text) in readers.items():
        path = _model_file(sparse, stem)
        results.append(binary(path) if path.suffix == ".bin" else text(path))
    cameras, images, (xyz, rgb) = results
    return cameras, images, xyz, rgb


def quaternion_to_rotation(q) -> np.ndarray:
    """(3, 3) rotation of quaternion q = (w, x, y, z), normalised first."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _intrinsics(camera: ColmapCamera, source: Path) -> np.ndarray:
    """(3, 3) K of a supported camera at its own size; DataError naming the model otherwise."""
    p = camera.params
    if camera.model not in SUPPORTED_MODELS:
        raise DataError(
            f"{source}: camera {camera.id} uses the {camera.model} camera model; supported: "
            f"{', '.join(SUPPORTED_MODELS)} (undistort the images first, e.g. with `colmap image_undistorter`)"
        )
    which = f"{source}: camera {camera.id} ({camera.model})"
    if not np.isfinite(p).all():
        raise DataError(f"{which} has non-finite parameters ({_numbers(p)}); expected finite numbers")
    if camera.model == "PINHOLE":
        fx, fy, cx, cy = p
        focal = f"fx={fx:g}, fy={fy:g}"
    else:
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        focal = f"f={fx:g}"
    if not (fx > 0 and fy > 0):
        raise DataError(f"{which} has focal length {focal}; expected a positive focal length in pixels")
    if camera.model == "SIMPLE_RADIAL" and p[3] != 0.0:
        warnings.warn(f"{source}: camera {camera.id} is SIMPLE_RADIAL with k={p[3]:g}; the distortion is ignored")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _check_pose(image: ColmapImage, source: Path) -> None:
    """A DataError naming the image when its pose is not a rotation and translation: a zero or
    non-finite quaternion has no rotation to normalise to."""
    which = f"{source}: image {image.name!r} (id {image.id})"
    q = np.asarray(image.qvec, dtype=np.float64)
    if not np.isfinite(q).all() or np.linalg.norm(q) < 1e-6:
        raise DataError(
            f"{which} has rotation quaternion (w, x, y, z) = ({_numbers(q)}); expected a finite, non-zero quaternion"
        )
    if not np.isfinite(image.tvec).all():
        raise DataError(f"{which} has translation ({_numbers(image.tvec)}); expected finite numbers")


def _read_view(path: Path, camera: ColmapCamera, allowed: list[tuple[int, int]], size, source: str):
    """Image of `camera` from `path`: RGB (H, W, 3) and alpha (H, W, 1) or None, resized to `size`
    (width, height) when given. Its file must have one of the `allowed` sizes, else a DataError
    naming the file and both sizes."""
    if not path.is_file():
        raise DataError(f"{path}: {source} image not found")
    rgb, alpha = read_image(path)
    actual = (rgb.shape[1], rgb.shape[0])
    if actual not in allowed:
        expected = " or ".join(f"{w}x{h}" for w, h in dict.fromkeys(allowed))
        raise DataError(
            f"{path}: image is {actual[0]}x{actual[1]} but COLMAP camera {camera.id} ({camera.model}) "
            f"is {camera.width}x{camera.height}; expected {expected}"
        )
    if size is None:
        return rgb, alpha
    return resize_view(rgb, alpha, size)


def load_colmap(
    path, *, downscale: float = 1, hidden_dir=None, hidden_background=(1.0, 1.0, 1.0), holdout: int = 8,
    images: str = "images",
) -> SceneData:
    """Read a COLMAP scene folder: `images`/ and sparse/0/ (or sparse/) with cameras, images and
    points3D as .bin (preferred) or .txt.

    downscale: divide the image size by this (rounded, as 3DGS does); images come from
    `images`_<d>/ when that folder exists for an integer d (within a pixel of the target size, as
    resizing tools round differently; K follows the actual size), else are box-filtered from
    `images`/.
    hidden_dir: optional folder of hidden-view images with the scene images' file names, at the
    camera's size or the downscaled one. They fill each Camera's hidden (and hidden_alpha). RGBA
    hidden images are an object alone (hidden_level "object"), composited over hidden_background;
    RGB ones are whole views (hidden_level "scene"). An RGBA scene image is composited over black,
    as 3DGS multiplies a masked capture by its mask, which is what the renders are compared with.
    holdout: every holdout-th image in name order (index % holdout == 0) is a test view; 0 keeps
    all for training.
    Raises DataError for a missing folder or file, an unsupported camera model, an image whose size
    does not match its camera, a malformed or truncated model file, a model without 3-D points,
    a non-finite point, a zero or non-finite pose, or non-finite or non-positive intrinsics.
    """
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"{root}: COLMAP folder not found")
    sparse = root / "sparse" / "0"
    if not sparse.is_dir():
        sparse = root / "sparse"
        if not sparse.is_dir():
            raise DataError(f"{root}: no sparse/0/ (or sparse/) folder with the COLMAP model")
    cameras, colmap_images, xyz, rgb = read_model(sparse)
    if not colmap_images:
        raise DataError(f"{sparse}: the model has no registered images")
    if len(xyz) == 0:
        raise DataError(
            f"{_model_file(sparse, 'points3D')}: the model has no 3-D points; training places its anchors on them, "
            "so it needs at least one"
        )

    image_dir, resized_dir = root / images, root / f"{images}_{int(downscale)}"
    presized = downscale != 1 and float(downscale).is_integer() and resized_dir.is_dir()
    if presized:
        image_dir = resized_dir
    elif not image_dir.is_dir():
        raise DataError(f"{image_dir}: image folder not found")
    if hidden_dir is not None and not Path(hidden_dir).is_dir():
        raise DataError(f"{hidden_dir}: hidden-view image folder not found")

    train, test, hidden_alphas = [], [], []
    for index, image in enumerate(sorted(colmap_images.values(), key=lambda i: i.name)):
        if image.camera_id not in cameras:
            raise DataError(
                f"{sparse}: image {image.name!r} refers to camera {image.camera_id}, which is not in the model"
            )
        camera = cameras[image.camera_id]
        _check_pose(image, _model_file(sparse, "images"))
        K = _intrinsics(camera, _model_file(sparse, "cameras"))
        target = (round(camera.width / downscale), round(camera.height / downscale))
        if presized:
            allowed = [(target[0] + dx, target[1] + dy) for dx in (0, -1, 1) for dy in (0, -1, 1)]
            rgb_image, alpha = _read_view(image_dir / image.name, camera, allowed, None, "scene")
        else:
            allowed = [(camera.width, camera.height)]
            rgb_image, alpha = _read_view(image_dir / image.name, camera, allowed, target, "scene")
        if alpha is not None:  # as 3DGS reads a masked capture: the colour times its alpha (over black)
            rgb_image = composite(rgb_image, alpha, (0.0, 0.0, 0.0))
        height, width = rgb_image.shape[:2]
        K[0] *= width / camera.width
        K[1] *= height / camera.height
        viewmat = np.eye(4)
        viewmat[:3, :3], viewmat[:3, 3] = quaternion_to_rotation(image.qvec), image.tvec
        view = Camera(image.name, viewmat, K, width, height, rgb_image, alpha)
        if hidden_dir is not None:
            allowed = [(camera.width, camera.height), (width, height)]
            hidden, hidden_alpha = _read_view(Path(hidden_dir) / image.name, camera, allowed, (width, height), "hidden")
            view.hidden = hidden if hidden_alpha is None else composite(hidden, hidden_alpha, hidden_background)
            view.hidden_alpha = hidden_alpha
            hidden_alphas.append(hidden_alpha is not None)
        (test if holdout and index % holdout == 0 else train).append(view)

    scene = SceneData(root.name, train, test, xyz.astype(np.float32), rgb.astype(np.float32) / 255.0)
    if hidden_dir is not None:
        if len(set(hidden_alphas)) > 1:
            raise DataError(f"{hidden_dir}: some hidden images have an alpha channel and some do not")
        scene.hidden_kind, scene.hidden_name = "object", Path(hidden_dir).name
        scene.hidden_level = "object" if hidden_alphas[0] else "scene"
        scene.hidden_background = hidden_background if hidden_alphas[0] else None
    return scene
