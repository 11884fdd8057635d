"""Devices and data-parallel training (issue #25), on this CPU machine:

- two gloo processes on the loopback interface train a tiny ODMO (and A2M, the classifier) and
  end with the weights of one process training on the same global batches, to float tolerance;
- a run resumed on two processes from a one-process checkpoint ends where one process would;
- DVGAN trains on two processes (its noise is each rank's own: it runs, it is not compared);
- Ctrl-C on the launcher of `odmo train --nproc 2`, or on one of its processes, stops both, exit
  130, with the last completed epoch saved;
- a device that is absent is one line and exit 2, before anything is written.

The worker processes run test_training_loop.train (the tiny recipes) with the environment torchrun
would give them. The weights are compared after plain SGD steps (`with_sgd`): two runs whose
gradients agree to float rounding then agree to float rounding. Adam does not keep that promise:
its first steps move every weight by about lr whatever the gradient's size, so a gradient that is
rounding noise (the biases of ODMO's linear layers in front of batch norms have an exact gradient
of zero) becomes a step of +-lr, and two Adam runs differ by a few lr however exactly their
gradients agree. With Adam the test compares what is smooth: the logged losses.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from odmo_cli.checkpoint import load_checkpoint
from odmo_cli.cli import app
from odmo_cli.data.demo import demo_folder
from odmo_cli.training.distributed import Group

TESTS = Path(__file__).resolve().parent

WORKER = """
import json, sys
sys.path.insert(0, sys.argv[1])
from test_distributed import with_sgd
from test_training_loop import train
from odmo_cli.data.demo import load_demo
a = json.loads(sys.argv[2])
if a["sgd"]:
    with_sgd(a["kind"])
train(a["kind"], load_demo("humanact12"), a["out"], a["epochs"], a["resume"], **a["kw"])
"""

# SGD's constant rates (the loop sets every optimizer's rate): small steps for their gradients (ODMO's reach 1e5)
SGD_RATES = {"odmo": dict(lr=1e-9, lr_final=1e-9), "a2m": dict(lr=1e-4, lr_final=0.0),
             "classifier": dict(lr=1e-2, lr_final=0.0)}


def with_sgd(kind: str, monkeypatch=None) -> None:
    """Train `kind` with plain SGD instead of its Adam (see the module docstring); give it SGD_RATES[kind]."""
    from odmo_cli.training.a2m import A2MTrainer
    from odmo_cli.training.classifier import ClassifierTrainer
    from odmo_cli.training.odmo import ODMOTrainer

    cls = {"odmo": ODMOTrainer, "a2m": A2MTrainer, "classifier": ClassifierTrainer}[kind]

    def build_optimizers(self):
        return {"optimizer": torch.optim.SGD(self.model.parameters(), lr=self.tc.lr)}

    (monkeypatch.setattr if monkeypatch else setattr)(cls, "build_optimizers", build_optimizers)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def train_on(n: int, kind: str, out: Path, epochs: int, resume: Path | None = None, sgd: bool = False,
             timeout: float = 600, **kw):
    """Train with test_training_loop.train on n gloo processes over the loopback interface."""
    env = {**os.environ, "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(free_port()), "WORLD_SIZE": str(n),
           "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1"}
    args = json.dumps({"kind": kind, "out": str(out), "epochs": epochs, "resume": str(resume) if resume else None,
                       "sgd": sgd, "kw": kw})
    procs = [subprocess.Popen([sys.executable, "-c", WORKER, str(TESTS), args], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True,
                              env={**env, "RANK": str(r), "LOCAL_RANK": str(r)}) for r in range(n)]
    try:
        outputs = [p.communicate(timeout=timeout)[0] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for r, (p, text) in enumerate(zip(procs, outputs)):
        assert p.returncode == 0, f"rank {r} exited {p.returncode}:\n{text[-3000:]}"


def assert_same_weights(a: Path, b: Path, atol: float = 1e-6) -> None:
    sa, sb = load_checkpoint(a)["state_dict"], load_checkpoint(b)["state_dict"]
    assert sa.keys() == sb.keys()
    worst = max(float((sa[k].double() - sb[k].double()).abs().max()) for k in sa if sa[k].is_floating_point())
    assert worst < atol, f"largest weight difference {worst:.3g}"


# -- how a batch is shared ---------------------------------------------------------------------

def test_shares_cover_the_batch_once_and_weights_average_to_one():
    for n in (1, 2, 3, 7, 16):
        shares = [Group(rank=r, world_size=3).share(n) for r in range(3)]
        rows = [i for s, w in shares if w for i in range(n)[s]]
        assert rows == list(range(n))
        assert sum(w for _, w in shares) / 3 == pytest.approx(1.0)


# -- two processes against one -----------------------------------------------------------------

# 19 pairs a epoch in batches of 8: the last batch of 3 pairs splits 2 + 1 (unequal shares); no
# clipping, which would hide a gradient scaled by a wrong factor; mirrored clips and dropped decoder
# units, whose coins and masks each rank draws for the whole batch before taking its rows
ODMO_KW = dict(pairs_per_epoch=19, batch_size=8, grad_clip=0.0, mirror=True, decoder_dropout=0.3,
               model={"mix_energy_weight": 0.5})


def test_two_gloo_processes_train_odmo_as_one_process(tmp_path, monkeypatch):
    from test_training_loop import train
    from odmo_cli.data.demo import load_demo

    clips = load_demo("humanact12")
    train("odmo", clips, tmp_path / "adam1.pt", 2, **ODMO_KW)  # ODMO's own Adam: the losses agree
    train_on(2, "odmo", tmp_path / "adam2.pt", 2, **ODMO_KW)
    h1, h2 = load_checkpoint(tmp_path / "adam1.pt")["history"], load_checkpoint(tmp_path / "adam2.pt")["history"]
    assert [h["total"] for h in h2] == pytest.approx([h["total"] for h in h1], rel=1e-4)
    # the mixed decodes' term on its own (a small part of the total): each rank mixes its pairs by their own coins
    assert [h["mix_energy"] for h in h2] == pytest.approx([h["mix_energy"] for h in h1], rel=1e-4)
    with_sgd("odmo", monkeypatch)
    train("odmo", clips, tmp_path / "one.pt", 2, **ODMO_KW, **SGD_RATES["odmo"])
    train_on(2, "odmo", tmp_path / "two.pt", 2, sgd=True, **ODMO_KW, **SGD_RATES["odmo"])
    assert_same_weights(tmp_path / "one.pt", tmp_path / "two.pt")
    one, two = load_checkpoint(tmp_path / "one.pt"), load_checkpoint(tmp_path / "two.pt")
    # the same streams: the two-process file resumes as the one-process file would
    assert one["rng"]["numpy"] == two["rng"]["numpy"] and torch.equal(one["rng"]["torch"], two["rng"]["torch"])
    # the logged losses are the global batch's, and the batch norms' running statistics too
    assert two["history"][-1]["total"] == pytest.approx(one["history"][-1]["total"], rel=1e-4)
    assert torch.allclose(one["state_dict"]["encoder.fc.1.running_var"], two["state_dict"]["encoder.fc.1.running_var"],
                          rtol=1e-4, atol=1e-6)


def test_resume_on_two_processes_from_a_one_process_checkpoint(tmp_path, monkeypatch):
    from test_training_loop import train
    from odmo_cli.data.demo import load_demo

    clips = load_demo("humanact12")
    with_sgd("odmo", monkeypatch)
    kw = {**ODMO_KW, **SGD_RATES["odmo"]}
    train("odmo", clips, tmp_path / "straight.pt", 3, **kw)
    train("odmo", clips, tmp_path / "first.pt", 1, **kw)
    train_on(2, "odmo", tmp_path / "resumed.pt", 3, resume=tmp_path / "first.pt", sgd=True, **kw)
    assert load_checkpoint(tmp_path / "resumed.pt")["epoch"] == 3
    assert_same_weights(tmp_path / "straight.pt", tmp_path / "resumed.pt")


def test_a2m_and_classifier_match_one_process_and_dvgan_runs(tmp_path, monkeypatch):
    from test_training_loop import train
    from odmo_cli.data.demo import load_demo

    clips = load_demo("humanact12")
    for kind in ("a2m", "classifier"):
        with_sgd(kind, monkeypatch)
        train(kind, clips, tmp_path / f"{kind}1.pt", 2, **SGD_RATES[kind])
        train_on(2, kind, tmp_path / f"{kind}2.pt", 2, sgd=True, **SGD_RATES[kind])
        assert_same_weights(tmp_path / f"{kind}1.pt", tmp_path / f"{kind}2.pt")
    train_on(2, "dvgan", tmp_path / "dvgan.pt", 2)
    ckpt = load_checkpoint(tmp_path / "dvgan.pt")
    assert ckpt["epoch"] == 2 and all(torch.isfinite(t).all() for t in ckpt["state_dict"].values()
                                      if t.is_floating_point())


def worker_pid(launcher: subprocess.Popen, rank: int) -> int:
    """The pid of the launcher's process of `rank` (Linux: from /proc)."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == launcher.pid and \
                    f"RANK={rank}".encode() in (stat.parent / "environ").read_bytes().split(b"\0"):
                return int(stat.parent.name)
        except (OSError, IndexError, ValueError):
            continue
    raise AssertionError(f"no process of rank {rank} under the launcher")


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="finds the processes through /proc")
@pytest.mark.parametrize("where", ["launcher", "rank 1"])
def test_ctrl_c_stops_every_process_and_keeps_the_last_epoch(tmp_path, where):
    out = tmp_path / "clf.pt"
    cmd = [sys.executable, "-m", "odmo_cli", "train", "classifier", "--dataset", str(demo_folder("humanact12")),
           "--nproc", "2", "--epochs", "100000", "--checkpoint-every", "1", "--threads", "1", "--out", str(out)]
    launcher = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env={**os.environ, "GLOO_SOCKET_IFNAME": "lo"})
    try:
        deadline = time.monotonic() + 600
        while not out.exists() and launcher.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert out.exists(), launcher.communicate(timeout=60)
        os.kill(launcher.pid if where == "launcher" else worker_pid(launcher, 1), signal.SIGINT)
        stdout, stderr = launcher.communicate(timeout=120)
    finally:
        if launcher.poll() is None:
            launcher.kill()
    assert launcher.returncode == 130, stderr
    # rank 0 either takes the Ctrl-C (or the launcher's SIGTERM) itself or first sees rank 1 leave; it
    # keeps the last completed epoch either way
    assert ("interrupted: the last completed epoch is saved in" in stderr
            or "another training process stopped" in stderr), stderr
    assert "Traceback" not in stderr
    ckpt = load_checkpoint(out)
    assert ckpt["epoch"] >= 1 and len(ckpt["history"]) == ckpt["epoch"]


class ScriptedProcess:
    """A stand-in for one launched process: exits with `code` at poll number `at` (None: runs until
    signalled; a signal ends it at once, SIGTERM and SIGINT with 130 as `odmo train` does)."""

    def __init__(self, code, at):
        self.code, self.at, self.polls, self.returncode, self.signals = code, at, 0, None, []

    def poll(self):
        self.polls += 1
        if self.returncode is None and self.at is not None and self.polls >= self.at:
            self.returncode = self.code
        return self.returncode

    def send_signal(self, sig):
        self.signals.append(sig)
        self.returncode = -signal.SIGKILL if sig == signal.SIGKILL else 130


class FakeTime:
    """The launcher's clock: each sleep moves it on, so waits are counted in polls, not seconds."""

    def __init__(self):
        self.now = 0.0

    def sleep(self, seconds):
        self.now += seconds

    def monotonic(self):
        return self.now


def scripted_launch(monkeypatch, procs, logs=(), **kw):
    """`launch` over scripted processes; logs[r - 1] is what rank r writes to its log."""
    from odmo_cli.training import distributed

    made = iter(procs)

    def popen(*args, stdout=None, **_):
        proc = next(made)
        if stdout is not None and logs:
            stdout.write(logs[procs.index(proc) - 1].encode())
        return proc

    monkeypatch.setattr(distributed.subprocess, "Popen", popen)
    monkeypatch.setattr(distributed, "time", FakeTime())
    return distributed.launch(len(procs), ["classifier"], **kw)


@pytest.mark.parametrize("script, status", [
    ([(3, 2), (130, 3)], 130),     # rank 0 sees rank 1 leave before rank 1 has exited
    ([(3, 2), (130, 2)], 130),     # both seen in the same poll
    ([(130, 3), (3, 2)], 130),     # rank 0 interrupted on its own, rank 1 first to exit
    ([(3, 2), (130, 40)], 130),    # the other exits late, within the wait
    ([(None, None), (1, 2)], 1),   # rank 1 fails: rank 0 is stopped, the failure is the status
    ([(3, 2), (None, None)], 1),   # the other never exits: stopped after the wait, a failure
    ([(3, 2), (3, 2)], 1),         # no cause seen at all: a failure, never the 3
])
def test_the_launcher_takes_its_status_from_the_process_that_stopped_on_its_own(script, status, monkeypatch):
    procs = [ScriptedProcess(*s) for s in script]
    assert scripted_launch(monkeypatch, procs) == status
    # the launcher signals no one before it has a cause, or until the wait (5 s, 50 polls) is over
    assert all(not p.signals for p in procs if p.at is not None and p.at < 50)


def test_a_failed_rank_says_why_when_rank_0_only_saw_it_leave(monkeypatch, capfd):
    procs = [ScriptedProcess(3, 2), ScriptedProcess(1, 3)]
    assert scripted_launch(monkeypatch, procs, logs=["error: rank 1's own reason\n"]) == 1
    assert "rank 1's own reason" in capfd.readouterr().err


def test_a_failing_rank_stops_rank_0_with_sigterm_and_says_why(monkeypatch, capfd):
    procs = [ScriptedProcess(None, None), ScriptedProcess(1, 2)]
    assert scripted_launch(monkeypatch, procs, logs=["error: rank 1's own reason\n"]) == 1
    assert procs[0].signals == [signal.SIGTERM]  # rank 0 saves on SIGTERM, as on Ctrl-C
    assert "rank 1's own reason" in capfd.readouterr().err


def test_rank_0_failing_on_its_own_is_not_followed_by_the_others_logs(monkeypatch, capfd):
    procs = [ScriptedProcess(1, 2), ScriptedProcess(None, None)]
    assert scripted_launch(monkeypatch, procs, logs=["rank 1 was only stopped\n"]) == 1
    assert procs[1].signals == [signal.SIGTERM]
    assert "rank 1 was only stopped" not in capfd.readouterr().err


class Exited(Exception):
    """os._exit, recorded instead of ending the test process."""


@pytest.mark.parametrize("world, raised, status", [
    ("2", SystemExit(130), 130), ("2", SystemExit(None), 0), ("2", SystemExit("a message"), 1), ("2", None, 0),
    ("1", SystemExit(130), None), (None, SystemExit(130), None),
])
def test_a_training_process_leaves_with_the_commands_status_and_no_teardown(world, raised, status, monkeypatch, capsys):
    """A process of a multi-process run ends by os._exit with its command's status (gloo's threads
    may abort the interpreter's C++ teardown: SIGABRT instead of 130); any other run exits as usual."""
    import odmo_cli.cli as cli

    def command():
        if raised is not None:
            raise raised

    def exit_now(code):
        raise Exited(code)

    monkeypatch.setattr(cli, "app", command)
    monkeypatch.setattr(cli.os, "_exit", exit_now)
    if world is None:
        monkeypatch.delenv("WORLD_SIZE", raising=False)
    else:
        monkeypatch.setenv("WORLD_SIZE", world)
    if status is None:  # not one of several processes: sys.exit's status travels as usual
        with pytest.raises(SystemExit) as exc:
            cli.main()
        assert exc.value is raised
        return
    with pytest.raises(Exited) as exc:
        cli.main()
    assert exc.value.args == (status,)
    assert ("a message" in capsys.readouterr().err) == (status == 1)


# -- devices -----------------------------------------------------------------------------------

@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA GPU")
@pytest.mark.parametrize("command", [
    ["sample", "--action", "all", "--n", "1"],
    ["interpolate", "--action", "walk"],
    ["train", "--dataset", "DEMO", "--epochs", "1"],
    ["train", "a2m", "--dataset", "DEMO", "--epochs", "1"],
    ["train", "dvgan", "--dataset", "DEMO", "--epochs", "1"],
    ["train", "classifier", "--dataset", "DEMO", "--epochs", "1"],
    ["eval", "--repeats", "1"],
    ["bench", "--only", "sampling"],
])
def test_an_absent_device_is_one_line_and_exit_2_with_nothing_written(command, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    command = [str(demo_folder("humanact12")) if a == "DEMO" else a for a in command]
    res = CliRunner().invoke(app, [*command, "--device", "cuda"])
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: device cuda is not available"), res.output
    assert "auto, cpu" in lines[0]
    assert list(tmp_path.iterdir()) == []


def test_an_unknown_device_names_the_valid_ones():
    res = CliRunner().invoke(app, ["sample", "--action", "all", "--device", "tpu"])
    assert res.exit_code == 2
    assert res.output.strip() == "error: unknown device 'tpu'; valid: auto, cpu, cuda, cuda:N, mps"


def test_auto_is_the_cpu_without_a_gpu():
    from odmo_cli.device import resolve_device

    if not torch.cuda.is_available() and not torch.backends.mps.is_available():
        assert resolve_device("auto") == torch.device("cpu")
    assert resolve_device("cpu") == torch.device("cpu")


def test_bench_names_its_device(tmp_path):
    from odmo_cli.evaluation.bench import machine

    assert machine(torch.device("cpu"))["device"].startswith("cpu")
