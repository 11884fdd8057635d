"""Where the user keeps data, and which manifest describes a folder.

Lookup order for a dataset given by name: `--data DIR`, else the environment variable
`ODMO_DATA_DIR`, else the per-user data directory (`$XDG_DATA_HOME/odmo`, by default
`~/.local/share/odmo`). Below that root the release may sit directly or in one of the
manifest's `dirs` (e.g. `humanact12/HumanAct12`).
"""

from __future__ import annotations

import os
from pathlib import Path

from odmo_cli.data.manifest import Manifest, available_manifests, canonical_name, load_manifest
from odmo_cli.data.readers import HUMANACT12_NAME
from odmo_cli.errors import UserError

FOLDER_MANIFEST = "dataset.toml"  # written by `odmo data prepare` into a motion folder


def data_root(data: str | Path | None = None) -> Path:
    if data:
        return Path(data).expanduser()
    if os.environ.get("ODMO_DATA_DIR"):
        return Path(os.environ["ODMO_DATA_DIR"]).expanduser()
    base = os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share"
    return Path(base) / "odmo"


def looks_like(folder: Path, fmt: str) -> bool:
    if not folder.is_dir():
        return False
    if fmt == "cmu_a2m":
        return (folder / "pose_clip.csv").is_file()
    if fmt == "folder":
        return (folder / "index.csv").is_file()
    return any(HUMANACT12_NAME.match(p.name) for p in _first_npys(folder))


def _first_npys(folder: Path, limit: int = 20):
    for i, p in enumerate(folder.glob("*.npy")):
        if i >= limit:
            return
        yield p


def find_release(manifest: Manifest, data: str | Path | None = None) -> Path | None:
    """The folder holding the release under the data root, or None if it is not there."""
    root = data_root(data)
    for candidate in [root, *(root / d for d in manifest.dirs), root / manifest.name]:
        if looks_like(candidate, manifest.format):
            return candidate
    return None


def resolve(spec: str | Path, data: str | Path | None = None) -> tuple[Manifest, Path]:
    """A dataset name (`humanact12`) or a folder -> (its manifest, the folder holding it)."""
    spec_path = Path(spec).expanduser()
    if canonical_name(str(spec)) in available_manifests():
        manifest = load_manifest(canonical_name(str(spec)))
        folder = find_release(manifest, data)
        if folder is None:
            raise UserError(
                f"dataset {spec} not found under {data_root(data)}; pass --data DIR, set ODMO_DATA_DIR, "
                f"or run `odmo data fetch {spec}`"
            )
        return manifest, folder
    if spec_path.is_dir():
        return manifest_for_folder(spec_path), spec_path
    raise UserError(f"unknown dataset {spec!r}: not a folder; valid names: {', '.join(available_manifests())}, cmu")


def manifest_for_folder(folder: Path) -> Manifest:
    """Pick the manifest of a folder given by path, from what it contains."""
    if (folder / FOLDER_MANIFEST).is_file():
        return load_manifest(folder / FOLDER_MANIFEST)
    if looks_like(folder, "cmu_a2m"):
        return load_manifest("cmu_mocap")
    if looks_like(folder, "humanact12"):
        return load_manifest("humanact12")
    nested = [m for m in available_manifests() if find_release(load_manifest(m), folder) not in (None, folder)]
    if nested:
        raise UserError(f"{folder} holds a dataset below it; use the name with --data: e.g. `{nested[0]} --data {folder}`")
    if looks_like(folder, "folder"):
        raise UserError(
            f"{folder} has index.csv but no {FOLDER_MANIFEST}; name its dataset (e.g. `uestc --data {folder}`) "
            "or convert it with `odmo data prepare`"
        )
    raise UserError(f"{folder} is not a known dataset layout (HumanAct12 npy files, pose_clip.csv, or index.csv)")
