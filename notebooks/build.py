"""Execute the teaching notebooks headless and write their executed copies to docs/notebooks/.

    python notebooks/build.py          # every notebook (about 4 minutes on 2 CPU cores)
    python notebooks/build.py 03 06    # only the notebooks whose names start with these

The sources (notebooks/NN_name.ipynb) are stored without outputs; each copy has every figure and
animation in it, so it reads without a kernel. Each copy records in its metadata ("odmo_build")
the SHA-256 of its source's cells and of every shipped model file (odmo_cli/assets/models/*.pt)
its run opened; tests/test_notebooks.py fails when a copy is missing or either hash no longer
matches, until this command is run again. Each notebook runs in a fresh kernel, in a temporary
folder, with this repository first on its path and one thread per library. Copies are written
atomically (a failed run leaves the old copy in place).
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import nbformat

REPO = Path(__file__).resolve().parents[1]
SOURCES = REPO / "notebooks"
COPIES = REPO / "docs" / "notebooks"
MODELS = REPO / "odmo_cli" / "assets" / "models"
COMMAND = "python notebooks/build.py"
THREADS = {k: "1" for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}

# Run first in the kernel, then removed from the copy: records every shipped model file opened.
_WATCH = """
import os as _odmo_os, sys as _odmo_sys
_odmo_opened = set()
def _odmo_watch(event, args):
    if event == "open" and isinstance(args[0], (str, bytes, _odmo_os.PathLike)):
        path = _odmo_os.fsdecode(args[0])
        if path.endswith(".pt"):
            _odmo_opened.add(path)
_odmo_sys.addaudithook(_odmo_watch)
"""
_REPORT = "import json as _j, os as _o; print(_j.dumps(sorted({_o.path.realpath(p) for p in _odmo_opened})))"


def sources() -> list[Path]:
    return sorted(SOURCES.glob("[0-9][0-9]_*.ipynb"))


def source_sha256(nb) -> str:
    """SHA-256 of a notebook's cells: their types and texts, in order (not outputs or metadata)."""
    cells = [[c.cell_type, c.source] for c in nb.cells]
    return hashlib.sha256(json.dumps(cells, ensure_ascii=False).encode()).hexdigest()


def file_sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def stale_reasons(source: Path, copy: Path) -> list[str]:
    """Why the executed copy of `source` is out of date (empty when it is in sync)."""
    if not copy.is_file():
        return [f"{copy.relative_to(REPO)} is missing"]
    built = nbformat.read(copy, as_version=4).metadata.get("odmo_build", {})
    reasons = []
    if built.get("source_sha256") != source_sha256(nbformat.read(source, as_version=4)):
        reasons.append(f"{source.name} changed since its copy was built")
    for name, digest in built.get("models", {}).items():
        now = MODELS / name
        if not now.is_file():
            reasons.append(f"{copy.name} was built with the shipped {name}, which is not installed now")
        elif file_sha256(now) != digest:
            reasons.append(f"{copy.name} was built with another {name} than the one installed now")
    return reasons


def build(source: Path, timeout: int = 600) -> tuple[Path, float]:
    """Execute one source in a fresh kernel and write its copy; returns (copy, seconds)."""
    from nbclient import NotebookClient

    nb = nbformat.read(source, as_version=4)
    digest = source_sha256(nb)
    nb.cells.insert(0, nbformat.v4.new_code_cell(_WATCH))
    nb.cells.append(nbformat.v4.new_code_cell(_REPORT))
    env = dict(os.environ, **THREADS, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        client = NotebookClient(nb, timeout=timeout, kernel_name="python3", resources={"metadata": {"path": tmp}})
        client.execute(env=env)
    seconds = time.perf_counter() - start
    opened = json.loads(nb.cells[-1].outputs[-1]["text"])
    nb.cells = nb.cells[1:-1]
    for count, cell in enumerate((c for c in nb.cells if c.cell_type == "code"), start=1):
        cell.execution_count = count
        for out in cell.outputs:
            if "execution_count" in out:
                out["execution_count"] = count
    used = sorted(Path(p) for p in opened if Path(p).parent == MODELS.resolve())
    nb.metadata["odmo_build"] = {
        "source": f"notebooks/{source.name}",
        "source_sha256": digest,
        "models": {p.name: file_sha256(p) for p in used},
        "seconds": round(seconds, 1),
        "built": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}",
        "command": COMMAND,
    }
    COPIES.mkdir(parents=True, exist_ok=True)
    copy = COPIES / source.name
    with tempfile.NamedTemporaryFile("w", dir=COPIES, prefix=f".{source.name}.", suffix=".tmp",
                                     delete=False, encoding="utf-8") as f:
        nbformat.write(nb, f)
    os.chmod(f.name, 0o644)  # the temp file was made private; a copy is for everyone to read
    os.replace(f.name, copy)
    return copy, seconds


def main(prefixes: list[str]) -> int:
    chosen = [s for s in sources() if not prefixes or any(s.name.startswith(p) for p in prefixes)]
    if not chosen:
        print(f"no notebook in {SOURCES} starts with {', '.join(prefixes)}", file=sys.stderr)
        return 2
    for source in chosen:
        copy, seconds = build(source)
        print(f"{copy.relative_to(REPO)}: {seconds:.0f} s, {copy.stat().st_size / 1e6:.2f} MB", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
