"""The installed package must hold every source package, and our kernels never take the name `kernels`."""
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_is_listed_in_pyproject():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.relative_to(ROOT).parent.parts) for p in (ROOT / "securegs_warp").rglob("__init__.py")}
    found.add("securegs_warp.kernels")  # the top-level kernels/ folder, mapped by package-dir
    assert listed == found


def test_kernels_folder_does_not_shadow_another_kernels_package(tmp_path):
    fake = tmp_path / "site" / "kernels"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("WHO = 'someone else'\n")
    code = "import kernels, securegs_warp.kernels as ours; print(kernels.WHO, ours.__name__)"
    env = {"PYTHONPATH": f"{ROOT}:{tmp_path / 'site'}", "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["someone", "else", "securegs_warp.kernels"]
