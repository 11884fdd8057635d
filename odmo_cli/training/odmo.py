"""Training ODMO (main paper §3.2, eq. 5) on the shared loop: pairs of class-balanced clips,
Adam with gradient clipping, teacher forcing decayed linearly, and at the end the latent bank,
the mode mixtures and a report of what the model learnt.

An epoch draws `pairs_per_epoch` pairs (default: one per training clip), half of them of one
action (`same_class_fraction`, as the authors' release), each clip a random T-frame crop, mirrored
half the time with `mirror` (off by default, as in the paper and the release). On
several processes every rank draws each step's pairs, crops, teacher-forcing coins and code noise
for the whole batch and computes its share of the pairs (training/distributed.py).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from odmo_cli.checkpoint import dataset_description, float_state, load_checkpoint, odmo_config
from odmo_cli.data.dataset import MotionDataset, crops_from_start, mirror_map, mirror_rows, pair_indices
from odmo_cli.data.readers import ClipSet
from odmo_cli.device import model_device
from odmo_cli.errors import UserError
from odmo_cli.measures import diagnostics, plausibility
from odmo_cli.models.latent import ActionModes, assign, codes_and_ends, fit_modes, separation
from odmo_cli.models.losses import odmo_terms, total_loss
from odmo_cli.models.odmo import ODMO, ODMOConfig, preset_values, widen_pose_decoder
from odmo_cli.parallel import thread_count
from odmo_cli.training.configs import LoopConfig, PARTS, TrainConfig  # noqa: F401
from odmo_cli.training.distributed import training_group
from odmo_cli.training.loop import Progress, Trainer, TrainResult, dataset_shapes


def model_config_for(clips: ClipSet, overrides: dict | None = None, preset: str = "odmo") -> ODMOConfig:
    """ODMOConfig for the clips' dataset: its shapes, the preset's loss scales (models.odmo.PRESETS),
    then `overrides`."""
    return ODMOConfig.from_dict({**dataset_shapes(clips, ODMOConfig), **preset_values(preset, clips.manifest.name),
                                 **(overrides or {})})


class ODMOTrainer(Trainer):
    kind = "odmo"
    config_class = ODMOConfig
    model_class = ODMO
    init: dict | None = None  # where the weights started (start_from), kept in every checkpoint
    recipe = None  # training.recipe.Recipe of a recipe run, kept in every checkpoint with the phase
    phase = 0

    def build_optimizers(self) -> dict:
        trained = self.tc.parts()
        for name in PARTS:  # frozen parts get no gradients (and no Adam state)
            getattr(self.model, name).requires_grad_(name in trained)
        params = [p for p in self.model.parameters() if p.requires_grad]
        if self.tc.weight_decay:
            return {"optimizer": torch.optim.AdamW(params, lr=self.tc.lr, weight_decay=self.tc.weight_decay)}
        return {"optimizer": torch.optim.Adam(params, lr=self.tc.lr)}

    def setup(self) -> None:
        self.data = MotionDataset(self.clips, self.cfg.length, rng=self.np_rng, random_crop=self.tc.crops == "random")
        skeleton = self.clips.manifest.skeleton
        self.mirror_perm, self.mirror_axis = mirror_map(skeleton.joint_names), skeleton.ground_axes[0]

    def train_epoch(self) -> dict[str, float]:
        tc, model, opt, dev, gen = self.tc, self.model, self.optimizers["optimizer"], self.device, self.torch_gen
        model.train()
        for name in set(PARTS) - set(tc.parts()):  # frozen: batch norm keeps its running statistics too
            getattr(model, name).eval()
        teacher_rate = tc.teacher_rate(self.epoch)
        free = self.cfg.free_energy_weight > 0 and self.epoch >= tc.free_start()  # a second, free-running decode
        n_pairs = tc.pairs_per_epoch or len(self.train_idx)
        same = tc.same_class_fraction if tc.same_class_fraction >= 0 else None
        labels = self.clips.labels[self.train_idx]
        pairs = self.train_idx[pair_indices(labels, n_pairs, self.np_rng, same)]  # (n, 2)
        sums: dict[str, float] = {}
        for b in range(0, n_pairs, tc.batch_size):
            chunk = pairs[b:b + tc.batch_size]
            n = len(chunk)
            both = np.concatenate([chunk[:, 0], chunk[:, 1]])  # (2B,): pair k is rows k and B + k
            rows, weight = self.group.share(n)
            mine = np.r_[np.arange(n)[rows], n + np.arange(n)[rows]] if self.group.distributed else None
            motion, lab = self.data.batch(both, mine)  # (2B, T, J, 3), or this rank's pairs
            if tc.mirror:  # coins for the whole batch, in one process's order, then this rank's rows
                flip = self.np_rng.random(2 * n) < 0.5
                motion = mirror_rows(motion, flip if mine is None else flip[mine], self.mirror_perm, self.mirror_axis)
            motion, lab = motion.to(dev), lab.to(dev)
            # drawn for the whole batch, in the order of one process, then this rank's rows taken
            shape = (2 * n, self.cfg.length) if tc.tf_per == "clip" else (self.cfg.length,)
            teacher = torch.rand(shape, generator=gen, device=dev) < teacher_rate
            # scaled after the draw (x 1 is exact), so the other draws stay where they were
            eps = torch.randn((2 * n, self.cfg.latent_dim), generator=gen, device=dev) * tc.code_noise
            keep = self.dropout_masks(2 * n, gen) if tc.decoder_dropout else None  # (2, 2B, H)
            mix = torch.rand(n, generator=gen, device=dev) if self.cfg.mix_energy_weight else None  # (B,)
            if mine is not None:
                take = torch.from_numpy(mine).to(dev)
                eps, teacher = eps[take], teacher[take] if tc.tf_per == "clip" else teacher
                keep = None if keep is None else keep[:, take]
                mix = None if mix is None else mix[rows]
            out = self.net(motion, lab, teacher=teacher, eps=eps, free=free, keep=keep, mix=mix)
            terms = odmo_terms(out, motion, lab, self.cfg)
            loss = total_loss(terms, self.cfg)
            self.check_finite(loss)
            opt.zero_grad(set_to_none=True)
            (loss if weight == 1 else loss * weight).backward()
            if tc.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(model.parameters(), tc.grad_clip)
            opt.step()
            own = len(range(n)[rows]) if weight else 0  # pairs this rank computed
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach()) * own
            sums["total"] = sums.get("total", 0.0) + float(loss.detach()) * own
        sums = self.group.sum(sums)
        return {"clips": 2 * n_pairs, "teacher": teacher_rate, **({"phase": self.phase} if self.recipe else {}),
                **{k: v / n_pairs for k, v in sums.items()}}

    def dropout_masks(self, n: int, gen: torch.Generator) -> torch.Tensor:
        """The pose decoder's dropout for n clips: (2, n, H) multipliers, 0 or 1 / (1 - p)."""
        p = self.tc.decoder_dropout
        kept = torch.rand((2, n, self.cfg.motion_hidden), generator=gen, device=self.device) >= p
        return kept.float() / (1 - p)

    def start_from(self, ckpt: dict, source: str) -> None:
        """Start from another finished ODMO checkpoint's weights (a fine-tuning stage: this run's
        schedule, a fresh optimizer). Its model config must be this run's but for the loss terms and a
        wider pose decoder (--motion-hidden), which is widened to draw what the file drew."""
        if ckpt["dataset"] != dataset_description(self.clips):
            raise UserError(f"--init {source} was trained on {ckpt['dataset']['name']}, not {self.clips.manifest.name}")
        state = float_state(ckpt)
        narrow = state["motion.out.weight"].shape[1]  # the file's pose decoder width, read off its weights
        if self.model.cfg.motion_hidden < narrow:
            raise UserError(f"--motion-hidden {self.model.cfg.motion_hidden}: --init {source}'s pose decoder has "
                            f"{narrow} units; it can be widened, not narrowed")
        if self.model.cfg.motion_hidden > narrow:  # new units from this run's seeded initialisation
            state = widen_pose_decoder(state, self.model.state_dict())
        try:  # float16 values are copied into the float32 parameters
            self.model.load_state_dict(state)
        except RuntimeError as e:  # a size or a key that differs (an override of the architecture)
            raise UserError(f"--init {source}'s weights do not fit this model: {str(e).splitlines()[-1].strip()}") from None
        # the model config too, so that every stage's model values can be checked (older files lack it)
        self.init = {"source": source, "epoch": int(ckpt["epoch"]), "train_config": ckpt["train_config"],
                     "config": ckpt["config"], **({"init": ckpt["init"]} if ckpt.get("init") else {})}

    def extra_state(self) -> dict:
        out = {"init": self.init} if self.init else {}
        if self.recipe is not None:
            out.update(recipe=self.recipe.to_dict(), recipe_phase=self.phase)
        return out

    def load_extra_state(self, ckpt: dict) -> None:
        self.init = ckpt.get("init")
        self.phase = int(ckpt.get("recipe_phase", 0))

    def stopped_extra(self, snapshot: dict) -> dict:
        """A stopped run's latent bank and mode mixtures, from the last completed epoch's weights: the file
        samples, renders and evaluates as it is, and --resume still goes on exactly (it reads neither)."""
        model = ODMO(self.cfg)  # on the CPU, from the snapshot: the live model may be on a GPU, or mid-epoch
        model.load_state_dict(snapshot["state_dict"])
        bank = latent_bank(model, self.clips, self.train_idx)
        return {"latent_bank": bank, "modes": fit_modes(bank, self.cfg.n_classes, seed=self.tc.seed)}

    def enter_phase(self, phase: int, cfg: ODMOConfig, tc: TrainConfig) -> None:
        """Go on to a recipe's next phase in the same run: its model values (loss weights and readouts;
        the architecture is the run's), schedule and networks, a fresh optimizer; the weights and every
        random stream go on as they are."""
        self.phase, self.cfg, self.tc = phase, cfg, tc
        for module in (self.model, self.model.trajectory, self.model.motion):
            module.cfg = cfg
        # the last phase's gradients would otherwise stay on the parts this phase freezes, and count in clipping
        self.model.zero_grad(set_to_none=True)
        self.optimizers = self.build_optimizers()
        self.net = self.group.wrap(self.model)  # several processes: the wrapper syncs the networks this phase trains
        self.epoch = 0
        self.setup()

    def validate(self) -> dict[str, float]:
        """Reconstruction error of held-out clips from their mean code, with no teacher forcing."""
        idx = self.val_idx if len(self.val_idx) else self.train_idx
        return reconstruction_error(self.model, self.clips, idx)


def latent_bank(model: ODMO, clips: ClipSet, idx: np.ndarray, batch: int = 512) -> dict:
    """Codes of the canonical crop (first T frames) of clips[idx] -> plain-value dict of tensors."""
    data = MotionDataset(clips, model.cfg.length, random_crop=False)
    codes, ends = codes_and_ends(model, (data.batch(idx[b:b + batch])[0] for b in range(0, len(idx), batch)))
    return {
        "codes": codes,  # (N, D)
        "labels": torch.from_numpy(clips.labels[idx].copy()),  # (N,)
        "end_points": ends,  # (N, 3)
        "modes": torch.from_numpy(clips.modes[idx].copy()),  # (N,) -1 when unknown
        "names": [clips.names[i] for i in idx],
    }


@torch.no_grad()
def reconstruction_error(model: ODMO, clips: ClipSet, idx: np.ndarray, batch: int = 512) -> dict[str, float]:
    """Free-running reconstruction of clips[idx] from their mean codes and real end points (as at
    sampling time, no teacher forcing): mean per-joint position error and end-point error (dataset
    units), the error of the body about its root beside that of the clips' own action-mean body
    (diagnostics.body_error, diagnostics.mean_pose_error), and the body's speed and amplitude over the
    clips' own (diagnostics.damping_ratios), and the root height's amplitude over theirs ("height", the
    mean over actions of diagnostics.root_height_speed_and_amplitude's ratio)."""
    model.eval()
    dev = model_device(model)
    joint_err, end_err, recons, reals, labs = [], [], [], [], []
    for b in range(0, len(idx), batch):
        motion, labels = crops_from_start(clips, idx[b:b + batch], model.cfg.length)
        mu, _ = model.encode(motion.to(dev))
        _, recon = model.decode(mu, labels.to(dev), motion[:, -1, 0].to(dev))
        recon = recon.cpu()
        joint_err.append((recon - motion).norm(dim=-1).mean(dim=(1, 2)))
        end_err.append((recon[:, -1, 0] - motion[:, -1, 0]).norm(dim=-1))
        recons.append(recon.numpy())
        reals.append(motion.numpy())
        labs.append(labels.numpy())
    labs, recons, reals = np.concatenate(labs), np.concatenate(recons), np.concatenate(reals)
    damp = diagnostics.damping_ratios(recons, labs, reals, labs)
    up = model.cfg.up_axis
    height = diagnostics.class_ratios(diagnostics.root_height_speed_and_amplitude(recons, up)[1], labs,
                                      diagnostics.root_height_speed_and_amplitude(reals, up)[1], labs)
    return {"mpjpe": float(torch.cat(joint_err).mean()), "end_error": float(torch.cat(end_err).mean()),
            "body": diagnostics.body_error(recons, reals), "body_mean_pose": diagnostics.mean_pose_error(reals, labs),
            "speed": damp["speed"], "amplitude": damp["amplitude"], "height": diagnostics.mean_finite(height.values()),
            **plausible(recons, reals, labs, clips)}


PLAUSIBLE_REPORTED = ("foot_skate", "foot_contact", "root_up", "root_ground", "kinetic_fd", "coverage", "bone_var")


def plausible(recons: np.ndarray, reals: np.ndarray, labels: np.ndarray, clips: ClipSet) -> dict[str, float]:
    """The evaluation's plausibility measures (measures.plausibility.compare) of decodes against the clips
    they decode, overall only ("real_foot_skate" and "real_foot_contact": the clips' own, the floor)."""
    m = clips.manifest
    frame = plausibility.frame_for(m.skeleton, m.fps, reals)
    real = plausibility.measure(reals, frame, m.skeleton.parents)
    out = plausibility.compare(plausibility.measure(recons, frame, m.skeleton.parents), labels, real, labels,
                               plausibility.standardizer(real["kinetic"]))
    return {**{k: out[k] for k in PLAUSIBLE_REPORTED if k in out},
            "real_foot_skate": plausibility.share(real["skate"], real["steps"]),
            "real_foot_contact": plausibility.share(real["contact"], real["slots"])}


@torch.no_grad()
def noise_ceiling(model: ODMO, clips: ClipSet, idx: np.ndarray, seed: int, batch: int = 512) -> dict[str, float]:
    """diagnostics.noise_ceiling of the model's own posterior over clips[idx] (canonical crops): the
    speed and amplitude that the best squared-error decoder could reach under that noise, and the
    least body error about the root it could reach."""
    model.eval()
    mus, stds, motions, labels = [], [], [], []
    for b in range(0, len(idx), batch):
        motion, lab = crops_from_start(clips, idx[b:b + batch], model.cfg.length)
        mu, logvar = model.encode(motion.to(model_device(model)))
        mus.append(mu.cpu().numpy())
        stds.append(torch.exp(0.5 * logvar).cpu().numpy())
        motions.append(motion.numpy())
        labels.append(lab.numpy())
    c = diagnostics.noise_ceiling(np.concatenate(mus), np.concatenate(stds), np.concatenate(motions),
                              np.concatenate(labels), np.random.default_rng(seed), draws=2)
    return {"speed": c["speed"], "amplitude": c["amplitude"], "body": c["body"]}


def mode_homogeneity(clips: ClipSet, idx: np.ndarray, bank: dict, modes: dict, length: int) -> float:
    """diagnostics.mode_homogeneity (ODMO §4.3.1) of the canonical crops of clips[idx], each in the
    discovered mode its bank code falls in: percent by which the modes split each action's real
    motions into tighter groups (0: no better than one group). Actions with one clip are left out."""
    motions, labels = crops_from_start(clips, idx, length)
    labels = labels.numpy()
    codes = bank["codes"].numpy().astype(np.float64)
    found = np.zeros(len(idx), dtype=np.int64)
    for a in np.unique(labels):
        own = labels == a
        found[own] = assign(ActionModes.from_plain(modes["actions"][a]), codes[own])
    keep = np.isin(labels, [a for a in np.unique(labels) if np.count_nonzero(labels == a) >= 2])
    if not keep.any():
        return float("nan")
    return diagnostics.mode_homogeneity(motions.numpy()[keep], labels[keep], found[keep])


def finish(trainer: ODMOTrainer, extra: dict | None = None) -> dict:
    """Latent bank, mode mixtures, held-out reconstruction and latent separation; written into the checkpoint.
    The same reconstruction of the training clips ("train_"; their first crops) says whether the decoder
    fits the clips it learnt from: a body error there no lower than the action-mean body's is under-fitting,
    one far under the held-out error over-fitting. The held-out bodies against the training clips' own
    motions (diagnostics.retrieval_errors: the one with the nearest code, and the best one) say how much the
    decoder adds to a lookup, and how far it is from the best that any one training clip fits."""
    model, clips = trainer.model, trainer.clips
    bank = latent_bank(model, clips, trainer.train_idx)
    held = trainer.val_idx if len(trainer.val_idx) else trainer.train_idx
    held_bank = latent_bank(model, clips, held)
    fit = reconstruction_error(model, clips, trainer.train_idx)
    report = {
        "held_out_clips": int(len(held)),
        **{f"held_out_{k}": v for k, v in reconstruction_error(model, clips, held).items()},
        **{f"train_{k}": fit[k] for k in ("mpjpe", "body", "body_mean_pose")},
        **{f"ceiling_{k}": v for k, v in noise_ceiling(model, clips, trainer.train_idx, trainer.tc.seed).items()},
        **separation(bank["codes"].numpy(), bank["labels"].numpy(), held_bank["codes"].numpy(),
                     held_bank["labels"].numpy(), trainer.cfg.n_classes),
        "alpha": trainer.cfg.alpha,
    }
    if len(trainer.val_idx):  # the held-out bodies against the training clips' own motions
        length = trainer.cfg.length
        retrieved = diagnostics.retrieval_errors(
            crops_from_start(clips, held, length)[0].numpy(), held_bank["labels"].numpy(), held_bank["codes"].numpy(),
            crops_from_start(clips, trainer.train_idx, length)[0].numpy(), bank["labels"].numpy(), bank["codes"].numpy())
        report.update({f"held_out_body_{k}": v for k, v in retrieved.items()})
    modes = fit_modes(bank, trainer.cfg.n_classes, seed=trainer.tc.seed)
    report["mode_homogeneity"] = mode_homogeneity(clips, trainer.train_idx, bank, modes, trainer.cfg.length)
    report.update(extra or {})
    trainer.save({"latent_bank": bank, "modes": modes, "report": report})
    return report


def same_split(tc: TrainConfig, ckpt: dict) -> TrainConfig:
    """tc with the train/validation split of the checkpoint `ckpt` (its val_fraction and split seed):
    a stage drawn on another split would train on clips the earlier stages held out and validate on
    clips they trained on."""
    before = LoopConfig(**LoopConfig.pick(ckpt.get("train_config", {})))
    return replace(tc, val_fraction=before.val_fraction, split_seed=before.data_split_seed())


def train_odmo(clips: ClipSet, tc: TrainConfig, out: str | Path, *, preset: str = "odmo", init: Path | None = None,
               overrides: dict | None = None, resume: Path | None = None, progress: Progress | None = None,
               device: str = "cpu") -> TrainResult:
    """Train ODMO on clips (or resume a checkpoint), then write the final checkpoint with its bank.
    `preset`: the loss scales (models.odmo.PRESETS) under `overrides`, the model config's values.
    `init`: start from that finished checkpoint's weights, model config (`overrides` on top; the
    preset is not applied) and train/validation split. `device`: --device's value; under torchrun (or
    `launch`) one of several processes."""
    if init is not None and resume is not None:
        raise UserError("give either --init (start a new stage from a model's weights) or --resume, not both")
    with thread_count(tc.threads), training_group(device) as group:
        if resume is not None:
            if "recipe" in load_checkpoint(resume):
                raise UserError(f"{resume} is a recipe run's checkpoint: resume it with --recipe and the same file")
            trainer = ODMOTrainer.resumed(resume, clips, tc, out, group)
        elif init is not None:
            ckpt = load_checkpoint(init)
            if ckpt.get("kind") != "odmo":
                raise UserError(f"--init {init} holds a {ckpt.get('kind')!r} model, not odmo")
            kept = odmo_config(f"--init {init}", ckpt.get("config", {}))
            # files written before the config named its skeleton take the dataset's
            cfg = ODMOConfig.from_dict({"skeleton": clips.manifest.skeleton_name, "bones": "free",
                                        **ODMOConfig.pick(ckpt.get("config", {})), **(overrides or {})})
            if cfg.pose_frame != kept.pose_frame:  # same shapes, other meaning: would load silently
                raise UserError(f"--init {Path(init).name} draws poses in the {kept.pose_frame} frame; "
                                f"a stage from it keeps that frame, not {cfg.pose_frame}")
            trainer = ODMOTrainer(clips, cfg, same_split(tc, ckpt), out, group)
            trainer.start_from(ckpt, Path(init).name)
        else:
            trainer = ODMOTrainer(clips, model_config_for(clips, overrides, preset), tc, out, group)
        history = trainer.run(progress)
        return TrainResult(Path(out), trainer.epoch, history, finish(trainer))
