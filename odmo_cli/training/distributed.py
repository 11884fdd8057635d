"""Data-parallel training on several processes (torch.distributed): the process group, each
rank's share of a batch, and the launcher behind `odmo train --nproc N`.

How a run on N processes stays the run on one:
- every rank builds the same model from the same seed and draws from the same numpy and torch
  streams: the whole global batch is drawn (pairs, crops, noise) on every rank, and each rank
  computes only its share of the rows (`Group.share`). The streams stay in step, so a checkpoint
  written by rank 0 holds the state of all, and a run resumes on any number of processes;
- each rank's loss is its share's mean scaled by its share of the batch, so the gradients
  DistributedDataParallel averages are those of the global batch's mean: the single-process
  gradient (to float rounding);
- batch normalisation (ODMO's encoder) normalises with the statistics of the global batch, not
  the rank's share (`GlobalBatchNorm`), so its outputs and running statistics are also those of
  one process;
- rank 0 alone writes checkpoints (Trainer.is_writer), atomically.

Processes are found through the environment torchrun sets (RANK, WORLD_SIZE, LOCAL_RANK,
MASTER_ADDR, MASTER_PORT); `launch` sets the same for N processes on this machine. The backend is
gloo on the CPU and NCCL on CUDA GPUs (one GPU per process: cuda:LOCAL_RANK).
"""

from __future__ import annotations

import contextlib
import inspect
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from typing import Iterator

import torch
import torch.distributed as dist

from odmo_cli.device import resolve_device
from odmo_cli.errors import PeerStopped, UserError

# What a collective raises when another process of the run has gone: gloo raises a plain
# RuntimeError naming the closed connection, other backends a DistError.
PEER_GONE = ("Connection closed by peer", "Connection reset by peer", "Broken pipe")


def peer_lost(exc: BaseException) -> bool:
    """Whether `exc` is a collective failing because another process of the run has stopped."""
    return isinstance(exc, dist.DistError) or (isinstance(exc, RuntimeError) and any(m in str(exc) for m in PEER_GONE))


def env_rank() -> int:
    """This process's rank from torchrun's environment (0 when not started by a launcher)."""
    return int(os.environ.get("RANK", "0"))


def env_world_size() -> int:
    return int(os.environ.get("WORLD_SIZE", "1"))


@dataclass(frozen=True)
class Group:
    """This process's device and its place among the `world_size` processes of one training run."""

    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    rank: int = 0
    world_size: int = 1

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    def share(self, n: int) -> tuple[slice, float]:
        """This rank's rows of a global batch of n, and the weight of its mean loss.

        Contiguous rows, sizes differing by at most one; weight = world_size * rows / n, so that the
        average of the ranks' gradients is the gradient of the global mean. A rank left without
        rows (n < world_size) computes row 0 with weight 0: it must still take part in the step.
        """
        lo, hi = n * self.rank // self.world_size, n * (self.rank + 1) // self.world_size
        if hi == lo:
            return slice(0, 1), 0.0
        return slice(lo, hi), self.world_size * (hi - lo) / n

    def wrap(self, model: torch.nn.Module) -> torch.nn.Module:
        """The module to run forward passes through: on several processes, DistributedDataParallel
        around `model`, whose batch norms now use the global batch's statistics."""
        if not self.distributed:
            return model
        from torch.nn.parallel import DistributedDataParallel

        for m in model.modules():
            if type(m) is torch.nn.BatchNorm1d:
                m.__class__ = GlobalBatchNorm  # same parameters and buffers, same state-dict keys
        ids = [self.device.index] if self.device.type == "cuda" else None
        # every rank computes the same buffers (statistics of the same clips): nothing to send at
        # each forward pass (torch 2.13 renamed the switch; older versions know only the old name)
        quiet = ("forward_sync_buffers" if "forward_sync_buffers" in inspect.signature(DistributedDataParallel).parameters
                 else "broadcast_buffers")
        return DistributedDataParallel(model, device_ids=ids, **{quiet: False})

    def _comm_device(self) -> torch.device:
        return self.device if self.device.type == "cuda" else torch.device("cpu")

    def sum(self, values: dict[str, float]) -> dict[str, float]:
        """Each value summed over the ranks (one all_reduce); unchanged on one process."""
        if not self.distributed or not values:
            return values
        t = torch.tensor(list(values.values()), dtype=torch.float64, device=self._comm_device())
        dist.all_reduce(t)
        return dict(zip(values, t.tolist()))

    def any(self, flag: bool) -> bool:
        """True on every rank when `flag` is true on any rank."""
        if not self.distributed:
            return flag
        t = torch.tensor([float(flag)], device=self._comm_device())
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        return bool(t.item())

    def average_gradients(self, params) -> None:
        """Average the gradients of `params` over the ranks, in one all_reduce (for steps that
        cannot run through DistributedDataParallel, see training/dvgan.py)."""
        if not self.distributed:
            return
        grads = [p.grad for p in params if p.grad is not None]
        if not grads:
            return
        flat = torch.cat([g.reshape(-1) for g in grads])
        dist.all_reduce(flat)
        flat /= self.world_size
        offset = 0
        for g in grads:
            g.copy_(flat[offset:offset + g.numel()].view_as(g))
            offset += g.numel()


class GlobalBatchNorm(torch.nn.BatchNorm1d):
    """BatchNorm1d over the rows of all ranks in training mode (mean and variance of the global
    batch), on any backend: torch's SyncBatchNorm runs on GPUs only. The all_reduce is the
    differentiable one, so gradients flow through the shared statistics as on one process. A rank
    with no rows of its own (Group.share) adds its placeholder row: one extra row in that step."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.training or not dist.is_initialized():
            return super().forward(x)
        from torch.distributed.nn.functional import all_reduce

        dims = [0] + list(range(2, x.dim()))  # (N, C) or (N, C, L): statistics per channel C
        n = x.numel() // x.shape[1]
        local = torch.cat([x.sum(dims), x.pow(2).sum(dims), x.new_tensor([float(n)])])
        total = all_reduce(local)
        c = x.shape[1]
        count = total[-1]
        mean = total[:c] / count
        var = (total[c:2 * c] / count - mean.pow(2)).clamp_min(0)
        if self.track_running_stats and self.running_mean is not None:
            with torch.no_grad():
                self.num_batches_tracked += 1
                m = self.momentum if self.momentum is not None else 1.0 / float(self.num_batches_tracked)
                self.running_mean.lerp_(mean.detach(), m)
                self.running_var.lerp_((var * count / (count - 1).clamp_min(1)).detach(), m)
        shape = [1, c] + [1] * (x.dim() - 2)
        y = (x - mean.view(shape)) * torch.rsqrt(var.view(shape) + self.eps)
        return y * self.weight.view(shape) + self.bias.view(shape) if self.affine else y


@contextlib.contextmanager
def training_group(device: str | torch.device = "cpu") -> Iterator[Group]:
    """The Group of this process for one training run, joining the process group when started by
    torchrun or `launch` (left again at the end). A UserError for an absent device comes first."""
    world = env_world_size()
    dev = resolve_device(device)
    if world <= 1:
        with _stopping_on_signals():
            yield Group(dev)
        return
    if dev.type == "mps":
        raise UserError("training on several processes runs on cpu or cuda, not mps")
    if dev.type == "cuda":
        if ":" in str(device):
            raise UserError(f"--device {device} names one GPU; with several processes give --device cuda "
                            "(process k on a machine uses its GPU k)")
        dev = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(dev)
    joined = not dist.is_initialized()
    if joined:
        dist.init_process_group("nccl" if dev.type == "cuda" else "gloo", device_id=dev if dev.type == "cuda" else None)
    try:
        with _stopping_on_signals():
            yield Group(dev, dist.get_rank(), dist.get_world_size())
    finally:
        if joined:
            dist.destroy_process_group()


@contextlib.contextmanager
def _stopping_on_signals() -> Iterator[None]:
    """Inside the block SIGTERM becomes a KeyboardInterrupt, so the last completed epoch is written as
    for Ctrl-C: `kill`, a batch system's stop, or a launcher stopping the other processes when one
    fails or is interrupted. So does SIGINT where it was ignored (a job started in the background
    with `nohup ... &`). The handlers are restored after."""
    if not _main_thread():
        yield
        return

    def stop(signum, frame):
        raise KeyboardInterrupt

    old = {signal.SIGTERM: signal.signal(signal.SIGTERM, stop)}
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        old[signal.SIGINT] = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


# -- `odmo train --nproc N` ------------------------------------------------------------------------

def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def launch(nproc: int, argv: list[str], grace: float = 60.0, peer_wait: float = 5.0) -> int:
    """Run `odmo train <argv>` as `nproc` processes on this machine (as torchrun --standalone
    would) and return the exit status: 0, that of the process that stopped on its own, or 130 when
    interrupted. Rank 0 prints; the others' output is shown when one of them was the cause. Ctrl-C
    (SIGINT to this process) and a failing process stop all: each gets SIGINT or SIGTERM, rank 0
    writes the last completed epoch, and `grace` seconds after that signal whatever still runs is
    killed. A process that exits with PeerStopped's status (3) only saw another stop: the status is
    that other's (130 when it was interrupted on its own), whichever of the two the launcher sees
    exit first; if the other has not exited `peer_wait` seconds later, the rest are stopped and the
    status is 1."""
    if nproc < 1:
        raise UserError(f"--nproc must be at least 1, got {nproc}")
    env = {**os.environ, "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(_free_port()),
           "WORLD_SIZE": str(nproc), "LOCAL_WORLD_SIZE": str(nproc)}
    if sys.platform == "linux":
        env.setdefault("GLOO_SOCKET_IFNAME", "lo")  # all on this machine: talk over the loopback interface
    logs = [tempfile.TemporaryFile() for _ in range(1, nproc)]
    procs: list[subprocess.Popen] = []
    # Ctrl-C is noted, not raised: this loop must outlive it to pass it on and wait for rank 0's save
    interrupts: list[int] = []
    old = signal.signal(signal.SIGINT, lambda signum, frame: interrupts.append(signum)) if _main_thread() else None
    status, stopping, forwarded, lost = None, None, 0, None
    try:
        for rank in range(nproc):
            out = None if rank == 0 else logs[rank - 1]
            # own sessions: a terminal's Ctrl-C reaches only this launcher, which passes it on once
            procs.append(subprocess.Popen([sys.executable, "-m", "odmo_cli", "train", *argv],
                                          env={**env, "RANK": str(rank), "LOCAL_RANK": str(rank)},
                                          stdout=out, stderr=out, start_new_session=True))
        while [p.poll() for p in procs].count(None):  # poll every process: any() would stop at the first alive
            time.sleep(0.1)
            if len(interrupts) > forwarded:  # each Ctrl-C once to every process
                forwarded = len(interrupts)
                stopping = stopping or time.monotonic()
                _signal_all(procs, signal.SIGINT)
            if status is None and not interrupts:  # nothing signalled by this launcher yet
                cause = _cause(procs)
                if cause is not None:
                    # one stopped on its own: its status is the run's; stop the others (rank 0 saves)
                    status, stopping = cause, time.monotonic()
                    _signal_all(procs, signal.SIGTERM)
                elif any(p.returncode == PeerStopped.exit_code for p in procs):
                    # only "another process stopped" so far: the one that did may still be tearing
                    # down (it leaves the group before it exits); wait a little for its status
                    lost = lost or time.monotonic()
                    if time.monotonic() - lost > peer_wait:
                        status, stopping = 1, time.monotonic()
                        _signal_all(procs, signal.SIGTERM)
            if stopping is not None and time.monotonic() - stopping > grace:
                _signal_all(procs, signal.SIGKILL)
        if status is None:  # all ended within one poll
            cause = _cause(procs)
            status = cause if cause is not None else int(any(p.returncode for p in procs))
        if not interrupts and status and procs[0].returncode != status:
            for log in logs:  # rank 0 did not say why: show what the others said
                log.seek(0)
                sys.stderr.write(log.read().decode(errors="replace"))
        if interrupts:
            return 130
        return status if status >= 0 else 1  # killed by a signal: a failure
    finally:
        if old is not None:
            signal.signal(signal.SIGINT, old)
        _signal_all(procs, signal.SIGKILL)  # nothing outlives the launcher (a no-op when all ended)
        for log in logs:
            log.close()


def _cause(procs) -> int | None:
    """The exit status of the first process (by rank) that stopped on its own: not 0, not
    PeerStopped's (a process that only saw another leave)."""
    return next((p.returncode for p in procs if p.returncode not in (None, 0, PeerStopped.exit_code)), None)


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _signal_all(procs, sig) -> None:
    for p in procs:
        if p.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                p.send_signal(sig)
