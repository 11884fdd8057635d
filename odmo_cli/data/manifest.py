"""Dataset manifests: one TOML per dataset in `data_manifests/` (the repository's top level; inside the
installed package as `odmo_cli/data_manifests/`), plus file checksums.

A manifest names the dataset's source, licence, skeleton, frame, clip length and actions. The
companion `<name>.sha256` lists `sha256  relative/path` for every released file; the dataset
digest is the SHA-256 of that listing sorted by path, so one hash pins the whole release.
"""

from __future__ import annotations

import hashlib
import re
import sys
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from odmo_cli.errors import UserError
from odmo_cli.geometry.skeletons import Skeleton, get_skeleton

FORMATS = ("humanact12", "cmu_a2m", "folder")


@dataclass(frozen=True)
class Action:
    name: str  # command-line name, e.g. "warm_up"
    label: str  # the label as the release writes it, e.g. "Warm up" or "1"
    count: int  # clips in the release, as the papers report
    trials: tuple[str, ...] = ()  # source trials of this action (CMU: ids like "02_01"), for BVH import


@dataclass(frozen=True)
class Manifest:
    name: str
    title: str
    format: str
    skeleton_name: str
    up_axis: str
    scale: float
    fps: float
    clip_length: int
    actions: tuple[Action, ...]
    dirs: tuple[str, ...] = ()  # where the release may sit below a data root, e.g. "humanact12/HumanAct12"
    homepage: str = ""
    licence: str = ""
    citation: str = ""
    labels: str = ""
    sources: tuple[dict, ...] = ()
    files: tuple[dict, ...] = ()  # directly downloadable files: {url, path, sha256}
    digest: str = ""
    n_files: int = 0
    path: Path | None = field(default=None, compare=False)

    @property
    def skeleton(self) -> Skeleton:
        return get_skeleton(self.skeleton_name)

    @property
    def action_names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.actions)

    def action_index(self, name: str) -> int:
        """Index of an action given by name (case, spaces, hyphens and underscores don't matter)."""
        key = normalize_action(name)
        for i, a in enumerate(self.actions):
            if key in (a.name, normalize_action(a.label)):
                return i
        raise UserError(
            f"unknown action {name!r} for {self.name}; valid: {', '.join(self.action_names)}"
        )

    def checksums(self) -> dict[str, str]:
        """relative path -> sha256 of every released file (empty if the manifest has none)."""
        if self.path is None:
            return {}
        listing = self.path.with_suffix(".sha256")
        if not listing.is_file():
            return {}
        out = {}
        for line in listing.read_text().splitlines():
            if line.strip():
                digest, rel = line.split(maxsplit=1)
                out[rel.strip()] = digest
        return out


def normalize_action(name: str) -> str:
    return re.sub(r"[\s\-_]+", "_", name.strip().lower())


def manifest_dir() -> Path:
    """The manifests: inside the installed package (a wheel maps the repository's data_manifests/ to
    odmo_cli/data_manifests/), else beside the package in its checkout (an editable install, a clone)."""
    installed = Path(str(resources.files("odmo_cli"))) / "data_manifests"
    if installed.is_dir():
        return installed
    return Path(__file__).resolve().parents[2] / "data_manifests"


# Short names users may type for a dataset; the manifest's own name is the canonical one.
DATASET_ALIASES = {"cmu": "cmu_mocap"}


def canonical_name(name: str) -> str:
    """`cmu` -> `cmu_mocap`; any other name is returned unchanged."""
    return DATASET_ALIASES.get(name, name)


def available_manifests() -> tuple[str, ...]:
    return tuple(sorted(p.stem for p in manifest_dir().glob("*.toml")))


def load_manifest(name_or_path: str | Path) -> Manifest:
    """A shipped manifest by name (`humanact12`), or any manifest TOML by path."""
    path = Path(name_or_path)
    if path.suffix != ".toml":
        path = manifest_dir() / f"{name_or_path}.toml"
        if not path.is_file():
            raise UserError(
                f"unknown dataset {name_or_path!r}; valid: {', '.join(available_manifests())}"
            )
    if not path.is_file():
        raise UserError(f"manifest not found: {path}")
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"manifest {path} is not valid TOML: {exc}") from None
    return _parse(raw, path)


def _parse(raw: dict, path: Path) -> Manifest:
    try:
        actions = tuple(
            Action(a["name"], str(a.get("label", a["name"])), int(a.get("count", 0)),
                   tuple(str(t) for t in a.get("trials", ())))
            for a in raw["actions"]
        )
        checks = raw.get("checksums", {})
        m = Manifest(
            name=raw["name"], title=raw.get("title", raw["name"]), format=raw["format"],
            skeleton_name=raw["skeleton"], up_axis=raw["up_axis"], scale=float(raw.get("scale", 1.0)),
            fps=float(raw["fps"]), clip_length=int(raw["clip_length"]), actions=actions,
            dirs=tuple(raw.get("dirs", ())), homepage=raw.get("homepage", ""),
            licence=raw.get("licence", ""), citation=raw.get("citation", ""),
            labels=raw.get("labels", ""), sources=tuple(raw.get("sources", ())),
            files=tuple(raw.get("files", ())), digest=checks.get("digest", ""),
            n_files=int(checks.get("files", 0)), path=path,
        )
    except KeyError as exc:
        raise UserError(f"manifest {path} lacks the field {exc.args[0]!r}") from None
    if m.format not in FORMATS:
        raise UserError(f"manifest {path}: unknown format {m.format!r}; valid: {', '.join(FORMATS)}")
    if m.skeleton.up_axis != m.up_axis:
        raise UserError(f"manifest {path}: up axis {m.up_axis} disagrees with skeleton {m.skeleton.name}")
    return m


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def listing_digest(checksums: dict[str, str]) -> str:
    """SHA-256 over the sorted `sha256  path` lines: one hash for a whole release."""
    text = "".join(f"{checksums[rel]}  {rel}\n" for rel in sorted(checksums))
    return hashlib.sha256(text.encode()).hexdigest()
