"""Every command the README and docs/ show, run as written.

The commands are the `odmo ...` lines of the pages' ```sh blocks, the README's caption command, and the
```python blocks. All of them run in one folder, in the pages' order (README first), so that a line finds
what earlier lines wrote (`odmo export jump.npz` after `odmo sample ... --out jump.npz`), beside a
`shared/` that holds the data as the docs name it (`--data ../shared/data`).

- Default run: every line parses against the CLI (its command exists, its options exist and take its
  values); the quick lines (sampling, composing, rendering, export, info, modes, data list/info/show) and
  the Python blocks run to the end with exit 0.
- `-m slow`: the long lines (train, ship, eval, bench, data prepare) and those that need a trained
  baseline run as written, each until it has shown its work (a training's first epoch, an evaluation's
  first set) or for LONG_BUDGET seconds, then get Ctrl-C as a user would give it: no traceback, and a
  training leaves its checkpoint, which the lines after it use (the docs' `odmo.pt`, `a2m-lie.pt`, ...).
- USER_FILES: the few lines that name files only a user has (their own BVH folders, Action2Motion's
  released classifier): parsed, not run, each with its reason.

Inline spans in prose (`odmo eval --wide`) are fragments as often as commands: their commands and option
names must exist.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from odmo_cli.cli import app

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]  # docs/lab is history, not commands
CAPTION = "odmo render jump.npz --grid 1x4 --compare real"  # the README's figure caption
LONG = {("train",), ("ship",), ("eval",), ("bench",), ("data", "prepare"), ("data", "fetch")}
BASELINES = re.compile(r"(a2m|dvgan)-\w+\.pt")  # files only the (slow) training lines write
LONG_BUDGET = 240  # seconds a long line may run before Ctrl-C, if it has not shown its work
READY = re.compile(r"^((classifier )?epoch \d+/|evaluated set 1/|benchmarking \w+ \(\d)", re.M)  # work shown
USER_FILES = {
    "odmo data fetch NAME --to DIR": "a template: NAME is a manifest with [[files]] to download",
    "odmo data prepare my_bvh/ --format bvh --labels labels.csv --skeleton humanact12 --fps 20 --out my_data":
        "the user's BVH folder and labels (tests/test_bvh.py runs prepare on real BVH files)",
    "odmo data prepare cmu_bvh/ --format bvh --skeleton cmu20 --out cmu_from_bvh": "the CMU BVH release",
    "odmo data prepare other_bvh/ --format bvh --labels labels.csv --joint-map map.toml --unit cm --out mine":
        "the user's BVH folder, labels and joint map",
    "odmo train --recipe my_recipe.toml --dataset path/to/motion_folder --out mine.pt":
        "a template: the user's recipe and motion folder",
    "odmo eval --model odmo.pt --classifier action_recognition_model_humanact12.tar":
        "Action2Motion's released classifier, which the project does not ship",
}


CLI = typer.main.get_command(app)


def resolve(argv: list[str]):
    """(the command's words, the click command, the arguments left to it)."""
    group, words, args = CLI, [], list(argv)
    while hasattr(group, "commands"):
        if args and args[0] in group.commands:
            word = args.pop(0)
        elif words == ["train"]:
            word = "odmo"  # _TrainGroup's default
        else:
            break
        words.append(word)
        group = group.commands[word]
    return tuple(words), group, args


@dataclass(frozen=True)
class Shown:
    page: str  # e.g. "docs/generation.md"
    line: int
    text: str  # the command without its comment, or a Python block
    python: bool = False

    @property
    def argv(self) -> list[str]:
        return shlex.split(self.text, comments=True)[1:]

    @property
    def path(self) -> tuple[str, ...]:
        """The command's words before its first option or argument: ("data", "info"); `odmo train`
        without a model kind is `odmo train odmo`."""
        return resolve(self.argv)[0]

    @property
    def long(self) -> bool:
        return any(self.path[:len(p)] == p for p in LONG) or bool(BASELINES.search(self.text))

    @property
    def needs_data(self) -> bool:
        return "--compare real" in self.text or self.path == ("data", "info")

    def __str__(self) -> str:
        return f"{self.page}:{self.line}"


def shown(page: Path) -> list[Shown]:
    """The `odmo` lines of a page's sh blocks and its Python blocks, in order."""
    name, out, block, start = str(page.relative_to(REPO)), [], None, 0
    for i, line in enumerate(page.read_text().splitlines(), 1):
        if line.startswith("```"):
            if block is None:
                block, start = (line[3:].strip() or "text"), i
                body = []
            else:
                if block == "python":
                    out.append(Shown(name, start + 1, "\n".join(body), python=True))
                block = None
        elif block == "sh" and line.startswith("odmo "):
            assert not line.endswith("\\"), f"{name}:{i}: a command continued on the next line is not read here"
            out.append(Shown(name, i, line.split("  #")[0].strip()))
        elif block == "python":
            body.append(line)
    if page.name == "README.md":
        assert CAPTION in page.read_text(), "the README's caption command moved: update CAPTION"
        out.append(Shown(name, 0, CAPTION))
    return out


ALL = [s for page in PAGES for s in shown(page)]
COMMANDS = [s for s in ALL if not s.python]
QUICK = [s for s in ALL if s.python or not (s.long or s.text in USER_FILES)]
SLOW = [s for s in COMMANDS if s.long and s.text not in USER_FILES]


def test_the_pages_show_commands_of_every_kind():
    assert len(COMMANDS) >= 60 and len(QUICK) >= 30 and len(SLOW) >= 20
    assert {s.path[0] for s in COMMANDS} >= {"sample", "compose", "render", "export", "train", "eval", "bench", "data"}
    assert set(USER_FILES) <= {s.text for s in COMMANDS}, "a USER_FILES line is no longer shown"


@pytest.mark.parametrize("s", COMMANDS, ids=str)
def test_every_shown_command_parses(s):
    """The command exists and its options and values parse (click's own checks, before any work)."""
    path, command, args = resolve(s.argv)
    assert path and not hasattr(command, "commands"), f"{s}: {s.text}: not a command"
    ctx = command.make_context(" ".join(("odmo",) + path), list(args), resilient_parsing=False)
    ctx.close()


INLINE = re.compile(r"`(odmo [^`]*)`")


def test_inline_commands_name_real_commands_and_options():
    wrong = []
    for page in PAGES:
        for text in INLINE.findall(page.read_text()):
            _, command, _ = resolve(shlex.split(text.replace("|", " "))[1:])
            known = {o for p in command.params for o in p.opts} | {"--help", "-h"}
            wrong += [f"{page.name}: `{text}`: {o}" for o in re.findall(r"(?<![\w-])--[\w-]+", text) if o not in known]
    assert wrong == []


# -- running them ----------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """A folder beside `shared/` (the data where the docs say, if the tests have it), holding what a
    user brings: a trained ODMO file (the shipped one's copy: the slow run replaces it by its own
    training), a clip to go on from, and the repository's recipes."""
    from odmo_cli.checkpoint import shipped_file
    from odmo_cli.data.demo import demo_folder

    top = tmp_path_factory.mktemp("docs")
    ws = top / "work"
    ws.mkdir()
    data = os.environ.get("ODMO_DATA_DIR")
    if data:
        (top / "shared").symlink_to(Path(data).resolve().parent)
        (top / "HumanAct12").symlink_to(Path(data).resolve() / "humanact12" / "HumanAct12")
    (ws / "recipes").symlink_to(REPO / "recipes")
    shutil.copy(shipped_file("humanact12", "odmo"), ws / "odmo.pt")
    shutil.copy(sorted((demo_folder("humanact12")).rglob("*.npy"))[0], ws / "clip.npy")
    return ws


def _skip_without_data(s: Shown) -> None:
    if (s.needs_data or s.long) and not os.environ.get("ODMO_DATA_DIR"):
        pytest.skip("needs the datasets (ODMO_DATA_DIR)")
    if re.search(r"--device (cuda|mps)", s.text):
        import torch

        if not (torch.cuda.is_available() or torch.backends.mps.is_available()):
            pytest.skip("needs a GPU")


@pytest.mark.parametrize("s", QUICK, ids=str)
def test_quick_commands_run_as_written(s, workspace, monkeypatch):
    _skip_without_data(s)
    monkeypatch.chdir(workspace)
    if s.python:
        exec(compile(s.text, str(s), "exec"), {"__name__": "__docs__"})
        return
    res = CliRunner(env={"COLUMNS": "80"}).invoke(app, s.argv)
    assert res.exit_code == 0, f"{s}: {s.text}\n{res.output}"
    if s.page == "README.md":
        assert all(len(line) <= 80 for line in res.stdout.splitlines()), f"{s.text}: wider than 80 columns"


def _run_until_shown(argv: list[str], cwd: Path, budget: float) -> tuple[int, str, bool]:
    """Run `odmo argv` in cwd; Ctrl-C once it shows its work (READY) or after `budget` seconds.
    Returns (exit code, output, whether it was interrupted)."""
    proc = subprocess.Popen([sys.executable, "-m", "odmo_cli", *argv], cwd=cwd, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env={**os.environ, "COLUMNS": "120"})
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    deadline, interrupted = time.monotonic() + budget, False
    while proc.poll() is None:
        if time.monotonic() > deadline or READY.search("".join(lines)):
            proc.send_signal(signal.SIGINT)
            interrupted = True
            break
        time.sleep(0.5)
    try:
        code = proc.wait(timeout=300)
    except subprocess.TimeoutExpired:
        proc.kill()
        code = proc.wait()
    reader.join(timeout=10)
    return code, "".join(lines), interrupted


ORDERED_SLOW = sorted(SLOW, key=lambda s: ("training" not in s.page, "evaluation" not in s.page))


@pytest.mark.slow
@pytest.mark.parametrize("s", ORDERED_SLOW, ids=str)
def test_long_commands_start_as_written(s, workspace):
    """The training lines first (they write the files the others use), then evaluation's, then the rest."""
    _skip_without_data(s)
    if "other_project.npz" in s.text and not (workspace / "other_project.npz").exists():  # "motions made elsewhere"
        from odmo_cli.checkpoint import load_model
        from odmo_cli.generation.generate import sample

        sample(load_model("humanact12"), ["all"], 5, seed=0).save(workspace / "other_project.npz")
    for name in ("a.pt", "b.pt"):
        if f" {name}" in s.text and not (workspace / name).exists():
            shutil.copy(workspace / "odmo.pt", workspace / name)
    if "--config my.toml" in s.text:
        (workspace / "my.toml").write_text(_toml_block(REPO / "docs" / "training.md", "[model]"))
    code, output, interrupted = _run_until_shown(s.argv, workspace, LONG_BUDGET)
    assert "Traceback" not in output, f"{s}: {s.text}\n{output[-3000:]}"
    if not interrupted:
        assert code == 0, f"{s}: {s.text}\n{output[-3000:]}"
    elif s.path[0] == "train":
        out = s.argv[s.argv.index("--out") + 1]
        assert READY.search(output) and (workspace / out).is_file(), f"{s}: no epoch or no {out}\n{output[-3000:]}"


def _toml_block(page: Path, first: str) -> str:
    """The ```toml block of `page` whose first line starts with `first`."""
    blocks = re.findall(r"```toml\n(.*?)```", page.read_text(), re.S)
    return next(b for b in blocks if b.startswith(first))
