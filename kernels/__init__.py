"""Warp kernels of securegs-warp, imported as ``securegs_warp.kernels`` (never as ``kernels``).

Pure Warp: no torch import here. Each module holds the kernels of one pipeline stage (projection,
binning, blending), of the training loss (ssim) or of the synthetic scenes' ray caster (raycast);
``records`` holds the packed per-Gaussian row that the projection writes and the blending reads;
``checks`` the input checks that a render replayed from a graph runs on the device.
"""
if __name__ != "securegs_warp.kernels":
    # Imported as the top-level name ``kernels`` only because the repository root is on sys.path
    # (python run from the checkout). That name belongs to PyPI's ``kernels`` project: hand it over
    # so that this folder can never shadow it.
    import importlib.machinery
    import importlib.util
    import os
    import sys

    _root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    _path = [p for p in sys.path if os.path.abspath(p or os.curdir) != _root]
    _spec = importlib.machinery.PathFinder.find_spec("kernels", _path)
    if _spec is None:
        raise ImportError(
            "no top-level package 'kernels' is installed; this folder is securegs_warp.kernels "
            "(import it as `securegs_warp.kernels`)"
        )
    _module = importlib.util.module_from_spec(_spec)
    sys.modules["kernels"] = _module
    _spec.loader.exec_module(_module)
