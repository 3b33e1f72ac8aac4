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
    "reads_as_folder",
]


def reads_as_folder(path_or_name) -> bool:
    """Whether ``load_scene`` reads this as a scene folder rather than a built-in scene's name: a
    COLMAP or Blender folder, or any other existing folder not named like a built-in scene (which it
    then refuses as holding no scene). A folder named like a built-in scene that holds no scene (a
    run's output called "garden", say) does not hide the built-in."""
    path = Path(path_or_name)
    if (path / "sparse").is_dir() or (path / "transforms_train.json").is_file():
        return True
    return path.is_dir() and not _builtin_name(path_or_name)


def _builtin_name(path_or_name) -> bool:
    return str(path_or_name) in SCENES or str(path_or_name) in SCENE_ALIASES


def load_scene(path_or_name, **kwargs) -> SceneData:
    """Load a scene by folder or built-in name; kwargs go to the loader it picks.

    A folder with sparse/ is COLMAP (:func:`load_colmap`), one with transforms_train.json is
    Blender (:func:`load_blender`); otherwise a built-in synthetic scene name ("synthetic",
    "default", "room", "garden") goes to :func:`make_synthetic_scene`. A scene folder wins over a
    built-in name; any other folder of that name (a run's output, say) does not (``reads_as_folder``).
    Anything else is a DataError.
    """
    path = Path(path_or_name)
    if reads_as_folder(path_or_name):
        if (path / "sparse").is_dir():
            return load_colmap(path, **kwargs)
        if (path / "transforms_train.json").is_file():
            return load_blender(path, **kwargs)
        raise DataError(f"{path}: neither a COLMAP folder (no sparse/) nor a Blender one (no transforms_train.json)")
    if _builtin_name(path_or_name):
        return make_synthetic_scene(str(path_or_name), **kwargs)
    raise DataError(
        f"{path_or_name}: no such scene folder, and not a built-in scene name "
        f"({', '.join(sorted(SCENES) + sorted(SCENE_ALIASES))})"
    )
