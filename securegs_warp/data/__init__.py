"""Scene data: cameras, images, hidden views and a sparse point cloud, from the built-in synthetic
generator or from COLMAP / NeRF-synthetic (Blender) folders. All views use the conventions in
:mod:`.cameras` (world-to-camera viewmat with OpenCV axes, K in pixels, float32 images in [0, 1]).
"""
from pathlib import Path

from .blender import load_blender
from .cameras import Camera, SceneData
from .colmap import load_colmap
from .errors import DataError
from .meshes import load_mesh
from .synthetic import SCENE_ALIASES, SCENES, make_synthetic_scene

__all__ = [
    "Camera", "SceneData", "DataError", "make_synthetic_scene", "load_colmap", "load_blender", "load_mesh", "load_scene",
    "is_scene_folder",
]


def is_scene_folder(path) -> bool:
    """Whether ``path`` is a folder of a real scene: COLMAP (with sparse/) or Blender (with
    transforms_train.json)."""
    path = Path(path)
    return (path / "sparse").is_dir() or (path / "transforms_train.json").is_file()


def load_scene(path_or_name, **kwargs) -> SceneData:
    """Load a scene by folder or built-in name; kwargs go to the loader it picks.

    A folder with sparse/ is COLMAP (:func:`load_colmap`), one with transforms_train.json is
    Blender (:func:`load_blender`); otherwise a built-in synthetic scene name ("synthetic",
    "default", "room", "garden") goes to :func:`make_synthetic_scene`. A scene folder wins over a
    built-in name; any other folder of that name (a run's output, say) does not. Anything else is a
    DataError.
    """
    path = Path(path_or_name)
    if (path / "sparse").is_dir():
        return load_colmap(path, **kwargs)
    if (path / "transforms_train.json").is_file():
        return load_blender(path, **kwargs)
    name = str(path_or_name)
    if name in SCENES or name in SCENE_ALIASES:
        return make_synthetic_scene(name, **kwargs)
    if path.is_dir():
        raise DataError(f"{path}: neither a COLMAP folder (no sparse/) nor a Blender one (no transforms_train.json)")
    raise DataError(
        f"{name}: no such scene folder, and not a built-in scene name "
        f"({', '.join(sorted(SCENES) + sorted(SCENE_ALIASES))})"
    )
