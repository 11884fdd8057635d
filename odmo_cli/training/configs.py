"""The trainers' configs: what every training loop shares (LoopConfig) and each model's trainer on top.

Kept free of torch so the command line can build its options from them (cli.settings) without
loading torch; each trainer module uses its own from here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from odmo_cli.config import Config, ConfigError, check_finite, knob


# what the data sets in a model config (training.loop.dataset_shapes; DVGAN's vocabulary from its actions,
# the classifier's input size from the joints), never a user, a recipe or a config file
DATA_SHAPES = ("n_joints", "n_classes", "length", "skeleton", "up_axis", "actions", "vocab", "input_size")


@dataclass
class LoopConfig(Config):
    """What every trainer's config has; each model's config subclasses it with its own defaults."""

    epochs: int = knob(100, "Epochs to train.", "schedule")
    batch_size: int = knob(64, "Clips per step.", "schedule")
    lr: float = knob(1e-3, "Adam's learning rate.", "schedule")
    lr_final: float = knob(0.0, "Cosine decay of the rate to this value over the epochs (0: constant).", "schedule")
    val_fraction: float = knob(0.1, "Held-out share of each action's clips (a split column in the data wins).", "data")
    # a stage started from another model's weights keeps that model's split (training.odmo), so its
    # validation clips stay unseen whatever its seed
    split_seed: int = knob(-1, "Seed of the train/validation split (-1: the run's --seed).", "data")
    val_every: int = knob(10, "Epochs between validations on the held-out clips (0: never).", "schedule")
    checkpoint_every: int = knob(25, "Epochs between checkpoints (one is always written at the end; 0: only then).",
                                 "schedule")
    seed: int = 0
    threads: int = 0  # torch intra-op threads while training; 0 leaves torch's default

    def __post_init__(self):
        check_finite(self)
        if self.epochs <= 0 or self.batch_size <= 0:
            raise ConfigError("epochs" if self.epochs <= 0 else "batch_size",
                              f"must be positive, got {min(self.epochs, self.batch_size)}")
        if self.lr <= 0:
            raise ConfigError("lr", f"must be positive, got {self.lr}")
        if self.lr_final < 0:
            raise ConfigError("lr_final", f"must be >= 0 (0: constant), got {self.lr_final}")
        if not 0 <= self.val_fraction < 1:
            raise ConfigError("val_fraction", f"must be in [0, 1), got {self.val_fraction}")
        if self.split_seed < -1:
            raise ConfigError("split_seed", f"must be a seed or -1 (the run's seed), got {self.split_seed}")
        for name in ("val_every", "checkpoint_every", "threads"):
            if getattr(self, name) < 0:
                raise ConfigError(name, f"must not be negative, got {getattr(self, name)}")

    def data_split_seed(self) -> int:
        """The seed the train/validation split is drawn with."""
        return self.seed if self.split_seed < 0 else self.split_seed

    def learning_rate(self, epoch: int) -> float:
        """The rate of 0-based `epoch`."""
        return cosine_rate(self.lr, self.lr_final or self.lr, epoch, self.epochs)


def cosine_rate(lr: float, lr_final: float, epoch: int, epochs: int) -> float:
    """Cosine decay from lr (epoch 0) to lr_final (the last of `epochs`)."""
    frac = epoch / max(epochs - 1, 1)
    return lr_final + 0.5 * (lr - lr_final) * (1 + math.cos(math.pi * frac))


PARTS = ("encoder", "trajectory", "motion")  # ODMO's networks: the LMP encoder, trajectory and pose generators


@dataclass
class TrainConfig(LoopConfig):
    epochs: int = 300
    batch_size: int = knob(256, "Pairs per step (each step sees twice as many clips).", "schedule")
    lr: float = 1e-3  # the paper's; constant unless lr_final says otherwise
    tf_start: float = knob(1.0, "Teacher-forcing rate at the first epoch.", "schedule")
    tf_end: float = knob(0.3, "Teacher-forcing rate once decayed (the release's 0.3).", "schedule")
    tf_epochs: int = knob(0, "Teacher forcing decays linearly from --tf-start to --tf-end over these epochs "
                             "(0: all).", "schedule")
    tf_per: str = knob("step", "Teacher-forcing coins: step (one per time step for the batch, the release's) or clip "
                               "(per clip and step).", "experimental")
    free_from: int = knob(-1, "First epoch (0-based) of the free-running L_energy (-1: once teacher forcing has "
                              "decayed; half the epochs when it decays over all).", "schedule")
    pairs_per_epoch: int = knob(0, "Pairs an epoch draws (0: as many as training clips).", "schedule")
    same_class_fraction: float = knob(0.5, "Share of same-action pairs (the release's 0.5; -1: independent random "
                                           "pairs).", "data")
    mirror: bool = knob(False, "Mirror each training clip with probability 1/2, left and right swapped (neither the "
                               "paper's nor the release's).", "experimental")
    grad_clip: float = knob(1.0, "Largest gradient norm (the release's 1; 0: no clipping).", "schedule")
    weight_decay: float = knob(0.0, "AdamW's decoupled weight decay (0: Adam, as in the paper and the release).",
                               "experimental")
    # variational dropout: the same units at every step, in what the two cells pass on
    decoder_dropout: float = knob(0.0, "Drop each of the pose decoder's hidden units with this probability in "
                                       "training, the same units at every step of a clip (0: off).", "experimental")
    # "first" holds the crops the latent bank, the mode mixtures and validation encode
    crops: str = knob("random", "Which frames of each training clip a batch holds: random (a fresh crop each time, "
                                "the release's) or first (the first T).", "data")
    # a stage that should change what sampling draws of one part and leave the rest as they are
    train_parts: str = knob("", "Train only these networks, comma-separated: encoder, trajectory, motion "
                                "(default: all); the others keep their weights.", "schedule")
    # L_es and the KL read the posterior itself, not z
    code_noise: float = knob(1.0, "Scale of the posterior noise on the codes the decoders see in training (1: the "
                                  "VAE's; 0: each crop's mean code, what sampling's mixtures are fitted on).",
                             "experimental")

    def __post_init__(self):
        super().__post_init__()
        bad = [p for p in self.parts() if p not in PARTS]
        if bad or (self.train_parts and not self.parts()):
            raise ConfigError("train_parts", f"has unknown part {(bad or [self.train_parts])[0]!r}; valid: "
                                             f"{', '.join(PARTS)} (comma-separated)")
        for name in ("tf_start", "tf_end"):
            if not 0 <= getattr(self, name) <= 1:
                raise ConfigError(name, f"must be in [0, 1], got {getattr(self, name)}")
        if self.tf_epochs < 0 or self.pairs_per_epoch < 0:
            raise ConfigError("tf_epochs" if self.tf_epochs < 0 else "pairs_per_epoch", "must not be negative")
        if self.free_from < -1:
            raise ConfigError("free_from", f"must be an epoch (or -1: once teacher forcing has decayed), got {self.free_from}")
        if self.tf_per not in ("step", "clip"):
            raise ConfigError("tf_per", f"must be step or clip, got {self.tf_per!r}")
        if self.crops not in ("random", "first"):
            raise ConfigError("crops", f"must be random or first, got {self.crops!r}")
        for name in ("weight_decay", "code_noise", "grad_clip"):
            if getattr(self, name) < 0:
                raise ConfigError(name, f"must be a number >= 0, got {getattr(self, name)}")
        if not 0 <= self.decoder_dropout < 1:
            raise ConfigError("decoder_dropout", f"must be in [0, 1), got {self.decoder_dropout}")
        if not (0 <= self.same_class_fraction <= 1 or self.same_class_fraction == -1):
            raise ConfigError("same_class_fraction", f"must be in [0, 1] (or -1: independent pairs), got "
                                                     f"{self.same_class_fraction}")

    def parts(self) -> list[str]:
        """The networks this run trains (ODMO's submodules; all when train_parts is empty)."""
        return [p.strip() for p in self.train_parts.split(",") if p.strip()] if self.train_parts else list(PARTS)

    def free_start(self) -> int:
        """The first epoch (0-based) that trains the free-running decode."""
        if self.free_from >= 0:
            return self.free_from
        return self.tf_epochs or self.epochs // 2

    def teacher_rate(self, epoch: int) -> float:
        span = self.tf_epochs or self.epochs
        frac = min(epoch / max(span - 1, 1), 1.0)
        return self.tf_start + (self.tf_end - self.tf_start) * frac


@dataclass
class A2MTrainConfig(LoopConfig):
    epochs: int = 500  # the paper gives iterations, not epochs; ~9 steps per HumanAct12 epoch
    batch_size: int = 128  # A.2
    lr: float = 2e-4  # A.2, Adam with betas (0.9, 0.999); constant (lr_final 0)
    weight_decay: float = knob(1e-5, "Adam's weight decay (A.2: 1e-5).", "schedule")
    teacher_rate: float = knob(0.6, "Teacher-forcing rate p_tf (§3.2.3, A.2: 0.6).", "schedule")
    lambda_kl: float = knob(-1.0, "Weight of the KL term (-1: the paper's for the dataset, 0.01 HumanAct12, "
                                  "else 0.1).", "losses")
    grad_clip: float = knob(0.0, "Largest gradient norm (0: no clipping, as in the paper).", "schedule")

    def __post_init__(self):
        super().__post_init__()
        if self.weight_decay < 0 or self.grad_clip < 0:
            raise ConfigError("weight_decay" if self.weight_decay < 0 else "grad_clip", "must be a number >= 0")
        if not 0 <= self.teacher_rate <= 1:
            raise ConfigError("teacher_rate", f"must be in [0, 1], got {self.teacher_rate}")


@dataclass
class DVGANTrainConfig(LoopConfig):
    # the paper runs 20,000 generator iterations with n_critic 10; at batch 64 on HumanAct12
    # (1191 clips, 19 critic steps an epoch) that is about 10,500 epochs
    epochs: int = 10500
    batch_size: int = 64  # not given in the paper
    lr: float = 1e-4  # Adam, §5.2; constant (lr_final 0)
    val_fraction: float = 0.0  # a GAN has no validation loss; a `split` column still holds out val/test
    val_every: int = 0
    betas: tuple[float, float] = (0.0, 0.9)  # not given; WGAN-GP's own choice (DVGAN builds on it)
    n_critic: int = knob(10, "Discriminator steps per generator step (§5.2: 10).", "schedule")
    gp_lambda: float = knob(10.0, "Weight of the gradient penalty (eq. 3: 10).", "losses")

    def __post_init__(self):
        self.betas = tuple(self.betas)
        super().__post_init__()
        if self.n_critic <= 0:
            raise ConfigError("n_critic", f"must be positive, got {self.n_critic}")
        if self.gp_lambda < 0:
            raise ConfigError("gp_lambda", f"must be a number >= 0, got {self.gp_lambda}")


SAMPLINGS = ("shuffle", "balanced", "length")


@dataclass
class ClassifierTrainConfig(LoopConfig):
    # Defaults: the shipped HumanAct12 recipe's settings (docs/lab/classifier.md).
    epochs: int = 200
    batch_size: int = 64
    lr: float = 1e-3
    lr_final: float = 1e-5  # cosine-decayed
    weight_decay: float = knob(0.0, "Adam's weight decay.", "schedule")
    dropout: float = knob(0.0, "Dropout between the GRU layers, in training.", "architecture")
    rotate: float = knob(0.0, "Augmentation: a random rotation about the up axis, up to this many degrees.", "data")
    mirror: bool = knob(True, "Augmentation: half the crops mirrored, left and right joints swapped.", "data")
    # a classifier that has learnt that a slowed-down punch is still a punch cannot see damped motion
    speed: float = knob(1.0, "Augmentation: playback speed drawn log-uniformly in [1/speed, speed] (1: off).",
                        "experimental")
    noise: float = knob(0.0, "Augmentation: std of Gaussian noise on every coordinate (dataset units).",
                        "experimental")
    val_fraction: float = 0.2
    val_every: int = 1  # held-out accuracy after every epoch
    sampling: str = knob("length", "Draws of an epoch: shuffle (every training clip once), length (every clip "
                                   "ceil(frames / T) times) or balanced (as many as clips, actions equally likely).",
                         "data")
    crop: str = knob("random", "Which frames: random (a random T-frame crop each epoch) or start (the first T).",
                     "data")
    grad_clip: float = knob(1.0, "Largest gradient norm (0: no clipping).", "schedule")
    hidden: int = knob(0, "GRU units (0: the dataset's preset).", "architecture")
    layers: int = knob(0, "GRU layers (0: the dataset's preset).", "architecture")

    def __post_init__(self):
        super().__post_init__()
        if not 0 <= self.dropout < 1:
            raise ConfigError("dropout", f"must be in [0, 1), got {self.dropout}")
        if not 1.0 <= self.speed <= 4.0:
            raise ConfigError("speed", f"must be in [1, 4] (1: no change), got {self.speed}")
        if not 0 <= self.rotate <= 180:
            raise ConfigError("rotate", f"must be in [0, 180] degrees, got {self.rotate}")
        if self.sampling not in SAMPLINGS:
            raise ConfigError("sampling", f"must be one of {', '.join(SAMPLINGS)}, got {self.sampling!r}")
        if self.crop not in ("random", "start"):
            raise ConfigError("crop", f"must be random or start, got {self.crop!r}")
        for name in ("noise", "weight_decay", "grad_clip", "hidden", "layers"):
            if getattr(self, name) < 0:
                raise ConfigError(name, f"must not be negative, got {getattr(self, name)}")
