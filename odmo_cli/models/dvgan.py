"""DVGAN (Lin & Amer, 2018): dense-validation WGAN-GP with a CNN or an RNN generator, conditioned
on the action name read as text (paper §4-5; equation numbers below are the paper's).

The networks work on normalised poses: joint positions with the first root at the origin,
flattened to F = J*3 features, minus a per-feature mean, over a per-feature std (§5.2 normalises
the same way; the stats are buffers, so they travel in the state dict). `generate` turns them
back into dataset units.

Shapes: B batch, T frames (the dataset's clip length), F = J*3, K hidden size, C actions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from odmo_cli.config import Config, ConfigError
from odmo_cli.errors import UserError

GENERATORS = ("cnn", "rnn")


def action_words(action: str) -> list[str]:
    """'lift_dumbbell' -> ['lift', 'dumbbell']: related names share words (and embeddings)."""
    return [w for w in action.lower().replace("-", "_").replace(" ", "_").split("_") if w]


@dataclass
class DVGANConfig(Config):
    n_joints: int = 24
    length: int = 60  # T, the output length; the generators make a 2T tape (final cut)
    actions: tuple[str, ...] = ()
    vocab: tuple[str, ...] = ()  # words of the action names; token i+1 is vocab[i], 0 pads
    generator: str = "cnn"  # cnn (eq. 5) | rnn (eq. 4)
    hidden: int = 256  # k = 256 for every module (§5.2)
    lm_hidden: int = 256  # language model: 2-layer LSTM, 256 units (§5.2)
    lm_layers: int = 2
    word_dim: int = 256  # not given in the paper (embeddings "learned from scratch"); = hidden
    rnn_layers: int = 2  # LSTM_diff: 2 layers of 256 (§5.2)
    rnn_latent: int = 256  # size of z_t in eq. 4; not given in the paper, chosen = k
    kernel: int = 3  # temporal kernel of the residual convs and the decoder; not given, chosen 3
    final_cut: bool = True  # generate 2T frames, keep a uniformly placed window of T (§4.1)
    shift_augment: bool = True  # shift D's input by up to +-T/2 with zero padding (§4.2)

    def __post_init__(self):
        self.actions, self.vocab = tuple(self.actions), tuple(self.vocab)
        if self.generator not in GENERATORS:
            raise ConfigError("generator", f"must be one of {', '.join(GENERATORS)}, got {self.generator!r}")
        if not self.vocab:
            self.vocab = tuple(sorted({w for a in self.actions for w in action_words(a)}))
        if self.length < 2 or self.n_joints < 1:
            raise UserError(f"DVGAN needs at least 2 frames and 1 joint, got {self.length} and {self.n_joints}")



    @property
    def n_features(self) -> int:
        return self.n_joints * 3

    @property
    def tape_length(self) -> int:
        return 2 * self.length if self.final_cut else self.length


# -- the condition ------------------------------------------------------------------------------

class LanguageModel(nn.Module):
    """Action name -> [h; c] of the top LSTM layer after the last word: (B,) labels -> (B, 2*lm_hidden).

    Eqs. 4-6 add h_txt to k-channel features, but [h; c] has 2*lm_hidden values, so every module
    that adds it first maps it with its own Linear (the paper does not say how the sizes meet).
    """

    def __init__(self, cfg: DVGANConfig):
        super().__init__()
        index = {w: i + 1 for i, w in enumerate(cfg.vocab)}
        words = [[index[w] for w in action_words(a)] or [0] for a in cfg.actions]
        width = max((len(w) for w in words), default=1)
        tokens = torch.zeros(len(words), width, dtype=torch.long)  # (C, L), 0 pads
        for i, w in enumerate(words):
            tokens[i, :len(w)] = torch.tensor(w)
        # buffers, not parameters: the vocabulary is fixed by the dataset and saved with the weights
        self.register_buffer("tokens", tokens)
        self.register_buffer("lengths", torch.tensor([len(w) for w in words], dtype=torch.long))
        self.embed = nn.Embedding(len(cfg.vocab) + 1, cfg.word_dim, padding_idx=0)
        self.lstm = nn.LSTM(cfg.word_dim, cfg.lm_hidden, cfg.lm_layers, batch_first=True)
        self.out_dim = 2 * cfg.lm_hidden

    def forward(self, labels: torch.Tensor) -> torch.Tensor:
        packed = nn.utils.rnn.pack_padded_sequence(self.embed(self.tokens), self.lengths.cpu(),
                                                   batch_first=True, enforce_sorted=False)
        _, (h, c) = self.lstm(packed)  # (layers, C, H) each, at every name's last word
        codes = torch.cat([h[-1], c[-1]], dim=-1)  # (C, 2H)
        return codes[labels]  # (B, 2H)


# -- generators -----------------------------------------------------------------------------------

class CNNGenerator(nn.Module):
    """Eq. 5: from one frame, residual modules double the frame rate; a plot module injects a
    Gaussian latent matrix and the text code at every resolution; a conv decodes the last one.

    With the final cut the tape has 2T frames; levels = ceil(log2(2T)) doublings reach
    2^levels >= 2T frames and the tape is the first 2T of them (T need not be a power of two).
    """

    def __init__(self, cfg: DVGANConfig, txt_dim: int):
        super().__init__()
        k, pad = cfg.hidden, cfg.kernel // 2
        self.cfg = cfg
        self.levels = math.ceil(math.log2(cfg.tape_length))
        # Plot_i = Conv1d ReLU[Conv1d(z_i) + h_txt]; size-1 convs (the paper does not give sizes),
        # and a per-level Linear brings the 2H text code to k channels so it can be added
        self.plot_z = nn.ModuleList(nn.Conv1d(k, k, 1) for _ in range(self.levels + 1))
        self.plot_txt = nn.ModuleList(nn.Linear(txt_dim, k) for _ in range(self.levels + 1))
        self.plot_out = nn.ModuleList(nn.Conv1d(k, k, 1) for _ in range(self.levels + 1))
        self.res_in = nn.ModuleList(nn.Conv1d(k, k, cfg.kernel, padding=pad) for _ in range(self.levels))
        self.res_out = nn.ModuleList(nn.Conv1d(k, k, cfg.kernel, padding=pad) for _ in range(self.levels))
        self.decode = nn.Conv1d(k, cfg.n_features, cfg.kernel, padding=pad)

    def plot(self, i: int, txt: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        b, k = len(txt), self.cfg.hidden
        z = torch.randn(b, k, 2 ** i, generator=generator, device=txt.device)  # (B, K, 2^i)
        return self.plot_out[i](F.relu(self.plot_z[i](z) + self.plot_txt[i](txt)[:, :, None]))

    def forward(self, txt: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """(B, 2H) text codes -> (B, tape, F) normalised poses."""
        h = self.plot(0, txt, generator)  # (B, K, 1)
        for i in range(1, self.levels + 1):
            up = F.interpolate(h, scale_factor=2, mode="linear", align_corners=False)  # up-sampling kind not given
            inner = F.interpolate(self.res_in[i - 1](h), scale_factor=2, mode="linear", align_corners=False)
            h = up + self.res_out[i - 1](F.relu(inner)) + self.plot(i, txt, generator)  # (B, K, 2^i)
        return self.decode(h)[:, :, :self.cfg.tape_length].transpose(1, 2)  # (B, tape, F)


class RNNGenerator(nn.Module):
    """Eq. 4: an MLP makes the first frame; an LSTM reads [Linear(a_{t-1}), plot_t] and its
    output, through a Linear, is added to the previous frame. Given a prefix it continues it."""

    def __init__(self, cfg: DVGANConfig, txt_dim: int):
        super().__init__()
        k = cfg.hidden
        self.cfg = cfg
        self.init_z, self.init_txt, self.init_out = nn.Linear(cfg.rnn_latent, k), nn.Linear(txt_dim, k), nn.Linear(k, k)
        self.first = nn.Linear(k, cfg.n_features)  # Decode(p_0)
        self.plot_z, self.plot_txt, self.plot_out = nn.Linear(cfg.rnn_latent, k), nn.Linear(txt_dim, k), nn.Linear(k, k)
        self.frame_in = nn.Linear(cfg.n_features, k)
        self.lstm = nn.LSTM(2 * k, k, cfg.rnn_layers, batch_first=True)
        self.diff = nn.Linear(k, cfg.n_features)

    def forward(self, txt: torch.Tensor, generator: torch.Generator, steps: int | None = None,
                prefix: torch.Tensor | None = None) -> torch.Tensor:
        """(B, 2H) text codes -> (B, steps, F) normalised poses (steps default: the tape).

        prefix (B, n, F): frames 0..n-1 are these exactly; the LSTM reads them, then continues.
        """
        steps = steps or self.cfg.tape_length
        b = len(txt)
        z = torch.randn(b, steps, self.cfg.rnn_latent, generator=generator, device=txt.device)  # (B, S, Z)
        txt_plot = self.plot_txt(txt)  # (B, K)
        if prefix is None:
            a = self.first(self.init_out(F.relu(self.init_z(z[:, 0]) + self.init_txt(txt))))  # (B, F)
        else:
            a = prefix[:, 0]
        frames, state = [a], None
        for t in range(1, steps):
            p = self.plot_out(F.relu(self.plot_z(z[:, t]) + txt_plot))  # (B, K)
            d, state = self.lstm(torch.cat([self.frame_in(a), p], dim=-1)[:, None], state)  # (B, 1, K)
            a = prefix[:, t] if prefix is not None and t < prefix.shape[1] else a + self.diff(d[:, 0])
            frames.append(a)
        return torch.stack(frames, dim=1)  # (B, S, F)


# -- discriminator ------------------------------------------------------------------------------

class Discriminator(nn.Module):
    """Eq. 6: size-1 conv encoding, residual down-sampling to one frame, a validation module
    (two size-1 convs matching features with the text code, averaged over frames) at every
    resolution, and a learned convex (softmax) combination of the scores."""

    def __init__(self, cfg: DVGANConfig, txt_dim: int):
        super().__init__()
        k, pad = cfg.hidden, cfg.kernel // 2
        self.levels = math.ceil(math.log2(cfg.length))  # T -> ... -> 1 frame
        self.encode = nn.Conv1d(cfg.n_features, k, 1)
        self.res_in = nn.ModuleList(nn.Conv1d(k, k, cfg.kernel, padding=pad) for _ in range(self.levels))
        self.res_out = nn.ModuleList(nn.Conv1d(k, k, cfg.kernel, padding=pad) for _ in range(self.levels))
        self.val_h = nn.ModuleList(nn.Conv1d(k, k, 1) for _ in range(self.levels + 1))
        self.val_txt = nn.ModuleList(nn.Linear(txt_dim, k) for _ in range(self.levels + 1))
        self.val_out = nn.ModuleList(nn.Conv1d(k, 1, 1) for _ in range(self.levels + 1))
        self.weights = nn.Parameter(torch.zeros(self.levels + 1))  # softmax -> convex weights

    def scores(self, x: torch.Tensor, txt: torch.Tensor) -> torch.Tensor:
        """(B, T, F) normalised poses, (B, 2H) text codes -> (B, levels+1) scores, finest first."""
        h = self.encode(x.transpose(1, 2))  # (B, K, T)
        out = []
        for i in range(self.levels + 1):
            if i > 0:
                # average pooling as the down-sampling (not given); ceil_mode keeps odd lengths' last frame
                down = F.avg_pool1d(h, 2, ceil_mode=True)
                h = down + self.res_out[i - 1](F.relu(F.avg_pool1d(self.res_in[i - 1](h), 2, ceil_mode=True)))
            match = F.relu(self.val_h[i](h) + self.val_txt[i](txt)[:, :, None])  # (B, K, T_i)
            out.append(self.val_out[i](match).mean(dim=(1, 2)))  # (B,)
        return torch.stack(out, dim=1)

    def convex_weights(self) -> torch.Tensor:
        return torch.softmax(self.weights, dim=0)

    def forward(self, x: torch.Tensor, txt: torch.Tensor) -> torch.Tensor:
        return self.scores(x, txt) @ self.convex_weights()  # (B,)


# -- pieces the training loop and the sampler share ---------------------------------------------

def final_cut(tape: torch.Tensor, length: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, S, F) tape -> ((B, length, F) window, (B,) starts), each start uniform in [0, S - length]."""
    starts = torch.randint(0, tape.shape[1] - length + 1, (len(tape),), generator=generator, device=tape.device)
    idx = starts[:, None] + torch.arange(length, device=tape.device)  # (B, length)
    return tape.gather(1, idx[:, :, None].expand(-1, -1, tape.shape[2])), starts


def temporal_shift(x: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Shift each (T, F) sequence by a uniform s in [-T//2, T//2] frames, zeros where nothing is known."""
    b, t, f = x.shape
    shifts = torch.randint(-(t // 2), t // 2 + 1, (b, 1), generator=generator, device=x.device)
    src = torch.arange(t, device=x.device)[None, :] - shifts  # (B, T): out[t] = x[t - s]
    valid = (src >= 0) & (src < t)
    out = x.gather(1, src.clamp(0, t - 1)[:, :, None].expand(-1, -1, f))
    return out * valid[:, :, None].to(x.dtype)


def gradient_penalty(critic, real: torch.Tensor, fake: torch.Tensor, generator: torch.Generator,
                     lam: float = 10.0) -> torch.Tensor:
    """Eq. 3's penalty: lam * E[(||grad critic(x_hat)|| - 1)^2], x_hat uniform on real-fake lines.

    critic: (B, ...) -> (B,). The graph is kept so the penalty trains the critic.
    """
    eps = torch.rand((len(real),) + (1,) * (real.dim() - 1), generator=generator, dtype=real.dtype, device=real.device)
    x_hat = (eps * real + (1 - eps) * fake).requires_grad_(True)
    grad, = torch.autograd.grad(critic(x_hat).sum(), x_hat, create_graph=True)
    return lam * ((grad.flatten(1).norm(dim=1) - 1) ** 2).mean()


class DVGAN(nn.Module):
    """Generator and discriminator, each with its own language model, and the pose statistics."""

    def __init__(self, cfg: DVGANConfig):
        super().__init__()
        self.cfg = cfg
        self.g_text, self.d_text = LanguageModel(cfg), LanguageModel(cfg)
        gen_cls = CNNGenerator if cfg.generator == "cnn" else RNNGenerator
        self.generator = gen_cls(cfg, self.g_text.out_dim)
        self.discriminator = Discriminator(cfg, self.d_text.out_dim)
        self.register_buffer("mean", torch.zeros(cfg.n_features))
        self.register_buffer("std", torch.ones(cfg.n_features))

    def generator_parameters(self):
        return list(self.g_text.parameters()) + list(self.generator.parameters())

    def discriminator_parameters(self):
        return list(self.d_text.parameters()) + list(self.discriminator.parameters())

    def set_stats(self, motions: torch.Tensor) -> None:
        """Per-feature mean and std from real (N, T, J, 3) motions with the first root at the origin."""
        flat = motions.flatten(2).flatten(0, 1)  # (N*T, F)
        std = flat.std(dim=0)
        self.mean.copy_(flat.mean(dim=0))
        # the first root is always 0, but the root moves, so its std is > 0; a floor guards degenerate data
        self.std.copy_(std.clamp_min(1e-3 * float(std.mean()) + 1e-8))

    def normalize(self, motions: torch.Tensor) -> torch.Tensor:
        return (motions.flatten(2) - self.mean) / self.std  # (B, T, J, 3) -> (B, T, F)

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        return (x * self.std + self.mean).unflatten(2, (self.cfg.n_joints, 3))  # (B, T, F) -> (B, T, J, 3)

    def fake(self, labels: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """(B,) labels -> (B, T, F) normalised generated poses, cut and moved like the real crops."""
        tape = self.generator(self.g_text(labels), generator)  # (B, tape, F)
        if self.cfg.final_cut:
            tape, _ = final_cut(tape, self.cfg.length, generator)
        motion = self.denormalize(tape)
        return self.normalize(motion - motion[:, :1, :1])  # first root at the origin, as the data

    def critic(self, x: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """(B, T, F) normalised poses -> (B,) scores."""
        return self.discriminator(x, self.d_text(labels))

    @torch.no_grad()
    def generate(self, labels: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """(N,) action indices -> (N, T, J, 3) motions in dataset units, first root at the origin."""
        motion = self.denormalize(self.fake(labels, generator))
        return motion - motion[:, :1, :1]  # exact zero (the round trip through the stats is not)

    @torch.no_grad()
    def complete(self, prefix: torch.Tensor, labels: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """(N, n, J, 3) prefixes with the first root at the origin -> (N, T, J, 3): frames 0..n-1
        are the prefix exactly, the rest continue it (RNN generator only)."""
        if self.cfg.generator != "rnn":
            raise UserError("motion completion needs a DVGAN-RNN model; this one has the CNN generator "
                            "(train one with: odmo train dvgan --generator rnn)")
        n = prefix.shape[1]
        x = self.generator(self.g_text(labels), generator, steps=self.cfg.length, prefix=self.normalize(prefix))
        motion = self.denormalize(x)
        motion[:, :n] = prefix
        return motion


def model_from_checkpoint(ckpt: dict) -> DVGAN:
    """The generator interface of odmo_cli.generate: a DVGAN with the checkpoint's weights."""
    model = DVGAN(DVGANConfig.from_saved(ckpt["config"]))
    model.load_state_dict(ckpt["state_dict"])
    return model
