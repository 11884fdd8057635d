"""What the shared training loop guarantees, for each of the four trainers (ODMO, Action2Motion,
DVGAN, the classifier), with tiny models on the demo clips:

- resume is exact: a run stopped by Ctrl-C in the middle of an epoch and resumed ends with the
  same weights, bit for bit, and the same loss history as the run never stopped;
- Ctrl-C keeps the state of the last completed epoch (the same weights as that epoch had);
- a non-finite loss stops training with a one-line TrainingError and leaves the last good
  checkpoint (or none) in place.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from odmo_cli.checkpoint import load_checkpoint
from odmo_cli.data.demo import demo_folder
from odmo_cli.data.locate import resolve
from odmo_cli.data.readers import read_dataset
from odmo_cli.errors import TrainingError, UserError
from odmo_cli.training.a2m import A2MTrainConfig, A2MTrainer, train_a2m
from odmo_cli.training.classifier import ClassifierTrainConfig, ClassifierTrainer, train_classifier
from odmo_cli.training.dvgan import DVGANTrainConfig, DVGANTrainer, train_dvgan
from odmo_cli.training.loop import TrainResult
from odmo_cli.training.odmo import ODMOTrainer, TrainConfig, train_odmo
from odmo_cli.training.recipe import train_recipe

KINDS = ("odmo", "a2m", "dvgan", "classifier")
TIMING = ("seconds", "clips_per_s")  # the only history entries that differ between runs


@pytest.fixture(scope="module")
def clips():
    manifest, root = resolve(demo_folder("humanact12"))
    return read_dataset(root, manifest)


def train(kind: str, clips, out, epochs: int, resume=None, progress=None, model=None, **kw):
    """One tiny training of `kind` (every trainer's own tiny recipe), one thread; `model`: ODMO's
    config values on top of its tiny recipe's."""
    if kind == "odmo":
        tc = TrainConfig(**{**dict(epochs=epochs, batch_size=16, val_every=0, checkpoint_every=0, val_fraction=0.0,
                                   seed=3, threads=1), **kw})
        return train_odmo(clips, tc, out, overrides={"motion_hidden": 16, "traj_hidden": 16, **(model or {})},
                          resume=resume, progress=progress)
    if kind == "a2m":
        tc = A2MTrainConfig(**{**dict(epochs=epochs, batch_size=16, lr=1e-2, val_fraction=0.0, val_every=0,
                                      checkpoint_every=0, threads=1), **kw})
        return train_a2m(clips, tc, out, representation=None if resume else "lie",
                         overrides={"length": 10, "hidden": 32, "z_dim": 4, "bank_size": 4},
                         resume=resume, progress=progress)
    if kind == "dvgan":
        tc = DVGANTrainConfig(**{**dict(epochs=epochs, batch_size=12, n_critic=2, checkpoint_every=0, seed=0,
                                        threads=1), **kw})
        return train_dvgan(clips, tc, out, generator="cnn", overrides={"hidden": 16, "lm_hidden": 8, "word_dim": 8,
                                                                       "rnn_latent": 8, "length": 16},
                           resume=resume, progress=progress)
    tc = ClassifierTrainConfig(**{**dict(epochs=epochs, batch_size=12, lr=3e-3, val_fraction=0.2, hidden=16,
                                         threads=1, seed=3, sampling="shuffle"), **kw})
    return train_classifier(clips, tc, out, resume=resume, progress=progress)


@pytest.mark.parametrize("entry", [train_odmo, train_a2m, train_dvgan, train_classifier, train_recipe])
def test_every_entry_point_takes_one_order_and_returns_a_train_result(entry):
    """(clips, a training config or recipe, out, *, the model's own options, resume, progress, device)
    -> TrainResult: everything after `out` by name, the shared options last in one order."""
    import inspect

    sig = inspect.signature(entry)
    names = list(sig.parameters)
    assert names[0] == "clips" and names[2] == "out" and names[-3:] == ["resume", "progress", "device"]
    assert all(p.kind is p.KEYWORD_ONLY for p in list(sig.parameters.values())[3:])
    if entry is not train_recipe:
        assert names[1] == "tc" and sig.return_annotation == "TrainResult"


def without_timing(history: list[dict]) -> list[dict]:
    return [{k: v for k, v in h.items() if k not in TIMING} for h in history]


class StepCounter:
    """Counts optimizer steps (every trainer steps Adam) and keeps the last optimizer stepped;
    raises KeyboardInterrupt at step `stop`."""

    def __init__(self, monkeypatch, stop: int | None = None):
        self.calls, self.stop, self.last = 0, stop, None
        real = torch.optim.Adam.step

        def step(opt, *args, **kwargs):
            self.calls += 1
            self.last = opt
            if self.calls == self.stop:
                raise KeyboardInterrupt
            return real(opt, *args, **kwargs)

        monkeypatch.setattr(torch.optim.Adam, "step", step)


@pytest.mark.parametrize("kind", KINDS)
def test_ctrl_c_mid_epoch_keeps_the_last_epoch_and_resume_is_exact(kind, clips, tmp_path, monkeypatch):
    """Bitwise: the same weights and the same loss history (but its timings) as the uninterrupted run."""
    epochs = 4
    full = tmp_path / "full.pt"
    # the run never stopped, checkpointing every epoch: the step count and the weights after each
    counter = StepCounter(monkeypatch)
    steps_at, weights_at = {}, {}

    def record(log):
        steps_at[log["epoch"]] = counter.calls
        weights_at[log["epoch"]] = load_checkpoint(full)["state_dict"]

    full_run = train(kind, clips, full, epochs, progress=record, checkpoint_every=1)
    assert isinstance(full_run, TrainResult) and full_run.out == full and full_run.epochs == epochs
    assert steps_at[3] - steps_at[2] >= 2  # epoch 3 has a second step to stop at
    # the same run, Ctrl-C at the second optimizer step of epoch 3: in the middle of the epoch
    monkeypatch.undo()
    StepCounter(monkeypatch, stop=steps_at[2] + 2)
    with pytest.raises(KeyboardInterrupt):
        train(kind, clips, tmp_path / "part.pt", epochs, checkpoint_every=1)
    monkeypatch.undo()
    part = load_checkpoint(tmp_path / "part.pt")
    assert part["kind"] == kind and part["epoch"] == 2 and len(part["history"]) == 2
    for key, value in weights_at[2].items():  # the last completed epoch's weights, not half of epoch 3
        assert torch.equal(part["state_dict"][key], value), key
    # resumed to the end: bit for bit the uninterrupted run
    resumed = train(kind, clips, tmp_path / "part.pt", epochs, resume=tmp_path / "part.pt")
    a, b = load_checkpoint(full), load_checkpoint(tmp_path / "part.pt")
    assert a["epoch"] == b["epoch"] == epochs
    for key in a["state_dict"]:
        assert torch.equal(a["state_dict"][key], b["state_dict"][key]), key
    assert without_timing(a["history"]) == without_timing(b["history"])
    if kind == "odmo":  # the latent bank comes from the same weights
        assert torch.equal(a["latent_bank"]["codes"], b["latent_bank"]["codes"])
        assert [h["total"] for h in full_run.history] == [h["total"] for h in resumed.history]
    if kind == "dvgan":  # 36 clips in batches of 12: 3 critic steps an epoch, counted across the resume
        assert a["d_steps"] == b["d_steps"] == 3 * epochs
    if kind == "classifier":
        assert a["report"]["train_accuracy"] == b["report"]["train_accuracy"]


@pytest.mark.parametrize("kind", KINDS)
def test_non_finite_loss_stops_and_keeps_the_last_good_checkpoint(kind, clips, tmp_path, monkeypatch):
    out = tmp_path / "m.pt"
    counter = StepCounter(monkeypatch)

    def poison(log):  # epoch 1 is saved; then a weight turns NaN, so epoch 2's loss is not finite
        if log["epoch"] == 1:
            with torch.no_grad():
                counter.last.param_groups[0]["params"][0].fill_(float("nan"))

    with pytest.raises(TrainingError, match=r"non-finite loss at epoch 2; the last good checkpoint \(epoch 1\)"):
        train(kind, clips, out, 3, progress=poison, checkpoint_every=1)
    ckpt = load_checkpoint(out)
    assert ckpt["epoch"] == 1
    assert all(torch.isfinite(v).all() for v in ckpt["state_dict"].values() if v.is_floating_point())


@pytest.mark.parametrize("kind", KINDS)
def test_a_loss_non_finite_from_the_start_writes_nothing(kind, clips, tmp_path, monkeypatch):
    trainer = {"odmo": ODMOTrainer, "a2m": A2MTrainer, "dvgan": DVGANTrainer, "classifier": ClassifierTrainer}[kind]
    build = trainer.build_model

    def poisoned(self):
        model = build(self)
        with torch.no_grad():
            next(model.parameters()).fill_(float("nan"))
        return model

    monkeypatch.setattr(trainer, "build_model", poisoned)
    with pytest.raises(TrainingError, match="non-finite loss at epoch 1; no checkpoint was written"):
        train(kind, clips, tmp_path / "m.pt", 2)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("kind", KINDS)
def test_resume_refuses_another_kind_of_model(kind, clips, tmp_path):
    other = "a2m" if kind == "odmo" else "odmo"
    train(other, clips, tmp_path / "other.pt", 1)
    with pytest.raises(UserError, match=f"cannot resume: .*holds a '{other}' model, not {kind}"):
        train(kind, clips, tmp_path / "m.pt", 2, resume=tmp_path / "other.pt")


def test_a2m_resume_keeps_the_representation(clips, tmp_path):
    train("a2m", clips, tmp_path / "lie.pt", 1)
    with pytest.raises(UserError, match="a2m-lie model, not xyz"):
        train_a2m(clips, A2MTrainConfig(epochs=2, threads=1), tmp_path / "x.pt", representation="xyz",
                  resume=tmp_path / "lie.pt")


def test_training_restores_the_thread_count(clips, tmp_path):
    before = torch.get_num_threads()
    train("classifier", clips, tmp_path / "m.pt", 1, threads=max(1, before - 1) if before > 1 else 2)
    assert torch.get_num_threads() == before
    assert np.isfinite(load_checkpoint(tmp_path / "m.pt")["history"][0]["loss"])


@pytest.mark.parametrize("how", ["SIGTERM", "SIGINT ignored by the shell"])
def test_kill_keeps_the_last_completed_epoch(tmp_path, how):
    """`kill PID` (SIGTERM), and Ctrl-C's SIGINT to a job the shell started in the background with
    SIGINT ignored (`nohup ... &`), stop a one-process training as Ctrl-C does: the last completed
    epoch is written (not only the last periodic checkpoint), exit 130, no traceback."""
    import os
    import signal
    import subprocess
    import sys

    out = tmp_path / "clf.pt"
    cmd = [sys.executable, "-m", "odmo_cli", "train", "classifier", "--dataset", str(demo_folder("humanact12")),
           "--epochs", "100000", "--checkpoint-every", "0", "--threads", "1", "--out", str(out)]
    ignore = (lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if how != "SIGTERM" else None
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=ignore)
    try:
        for line in proc.stderr:  # one line every 10 epochs
            if line.startswith("epoch 20/"):
                break
        proc.send_signal(signal.SIGTERM if how == "SIGTERM" else signal.SIGINT)
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stderr
    assert "interrupted: the last completed epoch is saved in" in stderr and "Traceback" not in stderr
    ckpt = load_checkpoint(out)
    assert ckpt["epoch"] >= 20 and len(ckpt["history"]) == ckpt["epoch"]
    assert os.path.getsize(out) > 0
