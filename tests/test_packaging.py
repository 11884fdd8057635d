"""An installed wheel (not an editable install) carries the dataset manifests of data_manifests/
and finds them where the repository's checkout does."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MANIFESTS = sorted(p.name for p in (REPO / "data_manifests").iterdir())


def test_the_checkout_reads_data_manifests():
    from odmo_cli.data.manifest import available_manifests, manifest_dir

    assert manifest_dir().resolve() == (REPO / "data_manifests").resolve()
    assert available_manifests() == ("cmu_mocap", "humanact12", "uestc")


def test_every_subpackage_is_listed_for_the_wheel():
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib

    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "odmo_cli").rglob("__init__.py")}
    assert found <= listed, sorted(found - listed)


def test_an_installed_wheel_finds_the_manifests(tmp_path):
    wheels = tmp_path / "wheels"
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", str(REPO), "--no-deps", "--no-build-isolation",
                            "--no-index", "-q", "-w", str(wheels)], capture_output=True, text=True, cwd=tmp_path)
    assert build.returncode == 0, build.stderr[-2000:]
    (wheel,) = wheels.glob("odmo-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    assert {f"odmo_cli/data_manifests/{m}" for m in MANIFESTS} <= names
    target = tmp_path / "site"
    install = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "-q",
                              "--target", str(target), str(wheel)], capture_output=True, text=True, cwd=tmp_path)
    assert install.returncode == 0, install.stderr[-2000:]
    probe = ("import odmo_cli; from odmo_cli.data.manifest import available_manifests, load_manifest, manifest_dir; "
             "print(odmo_cli.__file__); print(manifest_dir()); print(','.join(available_manifests())); "
             "print(len(load_manifest('humanact12').checksums()))")
    run = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=tmp_path,
                         env={"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stderr[-2000:]
    package, folder, names, checksums = run.stdout.split("\n")[:4]
    assert Path(package).is_relative_to(target)  # the installed copy, not this checkout
    assert Path(folder) == target / "odmo_cli" / "data_manifests"
    assert names == "cmu_mocap,humanact12,uestc" and int(checksums) == 1191
