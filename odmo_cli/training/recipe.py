"""A training recipe as a file: `odmo train --recipe FILE` trains ODMO from scratch in one run of
phases, under one seed and one set of random streams, and writes one checkpoint.

The file is TOML (docs/training.md, "Recipes"):

    dataset = "humanact12"     # the data it was made for (--dataset or --data may point elsewhere)
    preset = "odmo"            # the loss scales the model starts from (models.odmo.PRESETS)
    [model]                    # ODMOConfig values over the preset's, for the whole run
    [train]                    # TrainConfig values every phase shares
    [[phases]]                 # in order; each its own epochs, schedule and networks to train
    name = "..."
    epochs = 1000
    [phases.model]             # ODMOConfig values from this phase on: loss weights and readouts only

The seed is the run's (--seed), not the file's. A phase starts a fresh optimizer and its own schedule
(learning rate, teacher forcing) but nothing is re-seeded: the data order, crops and noise go on from
where the previous phase left them. Every key is checked against the configs: a misspelt one is refused
with the nearest valid name.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from odmo_cli.config import read_toml, refuse_unknown
from odmo_cli.errors import UserError
from odmo_cli.models.odmo_config import ODMOConfig, preset_values
from odmo_cli.training.configs import DATA_SHAPES, TrainConfig  # DATA_SHAPES: a recipe serves any dataset

TOP = ("dataset", "preset", "budget_hours", "model", "train", "phases")
PHASE = ("name", "model")
# what a phase may change of the model: the architecture and the data's shapes stay the run's
PHASE_MODEL = ("alpha", "sigma2", "same_class_deadzone", "recon_weight", "use_es", "use_traj", "use_cons",
               "up_weight", "traj_loss", "vel_weight", "energy_weight", "free_energy_weight", "height_weight",
               "mix_energy_weight", "root", "pose_loss", "bones", "foot_weight", "foot_axes", "bone_weight", "cons",
               "energy_on", "ground_weight")
# the split is the run's: a phase on another split would validate on clips it trained on
RUN_ONLY = ("val_fraction", "split_seed", "seed", "threads")


@dataclass
class Phase:
    name: str
    train: dict  # TrainConfig values of this phase (over the recipe's [train])
    model: dict = field(default_factory=dict)  # ODMOConfig values from this phase on


@dataclass
class Recipe:
    source: str
    dataset: str | None
    preset: str
    model: dict
    train: dict
    phases: list[Phase]
    budget_hours: float | None = None

    def train_config(self, phase: int, seed: int = 0) -> TrainConfig:
        """Phase `phase`'s TrainConfig in a run with `seed`."""
        return TrainConfig(**{**self.train, **self.phases[phase].train, "seed": seed})

    def model_values(self, phase: int) -> dict:
        """The ODMOConfig values over the preset in force in phase `phase`: [model], then each
        phase's [phases.model] up to it."""
        out = dict(self.model)
        for p in self.phases[:phase + 1]:
            out.update(p.model)
        return out

    @property
    def epochs(self) -> int:
        return sum(p.train["epochs"] for p in self.phases)

    def to_dict(self) -> dict:
        return {"source": self.source, "dataset": self.dataset, "preset": self.preset, "model": self.model, "train": self.train, "budget_hours": self.budget_hours,
                "phases": [{"name": p.name, "train": p.train, "model": p.model} for p in self.phases]}

    @classmethod
    def from_dict(cls, d: dict) -> "Recipe":
        return cls(d["source"], d["dataset"], d["preset"], d["model"], d["train"],
                   [Phase(p["name"], p["train"], p["model"]) for p in d["phases"]], d.get("budget_hours"))


def same_training(a: Recipe, b: Recipe) -> bool:
    """Whether two recipes train alike: where the file lies and the budget it states change no training."""
    same = {"source": "", "budget_hours": None}
    return a.to_dict() | same == b.to_dict() | same


def finished_run_differences(ckpt: dict, recipe: Recipe) -> list[str]:
    """What keeps checkpoint `ckpt` (a dict as stored) from being a finished run of `recipe` from scratch,
    one line each; [] for a file that is one: trained by the same recipe, to its last phase's last epoch,
    from no other file, with the last phase's model values."""
    if "recipe" not in ckpt:
        return ["not a recipe run (no recipe in the file)"]
    out = []
    if not same_training(Recipe.from_dict(ckpt["recipe"]), recipe):
        out.append(f"trained by another recipe than {Path(recipe.source).name}")
    last = len(recipe.phases) - 1
    if int(ckpt.get("recipe_phase", -1)) != last:
        out.append(f"stopped in phase {int(ckpt.get('recipe_phase', -1)) + 1} of {last + 1}")
    elif int(ckpt.get("epoch", 0)) != int(recipe.phases[last].train["epochs"]):
        out.append(f"stopped at epoch {ckpt.get('epoch')} of the last phase's {recipe.phases[last].train['epochs']}")
    if ckpt.get("init"):
        out.append("started from another file (--init), not from scratch")
    # the file's values with this version's defaults for settings it predates, against the preset's
    # loss scales for the data it was trained on under the recipe's values (as
    # training.odmo.model_config_for builds them)
    config = ODMOConfig.from_saved(ckpt.get("config", {})).to_dict()
    dataset = ckpt.get("dataset", {}).get("name") or recipe.dataset or ""
    expected = {**preset_values(recipe.preset, dataset), **recipe.model_values(last)}
    out += [f"model value {k} = {config.get(k)!r}, the recipe's {v!r}" for k, v in expected.items() if config.get(k) != v]
    return out


def _table(where: str, value) -> dict:
    if not isinstance(value, dict):
        raise UserError(f"{where} must be a table, got {type(value).__name__}")
    return value


def load_recipe(path: str | Path) -> Recipe:
    """The recipe in a TOML file; UserError naming the file and the problem for anything that is not
    a valid recipe (a misspelt key, a value a config refuses, a phase that changes the architecture)."""
    path = Path(path)
    raw = read_toml(path, "recipe")
    name = path.name
    refuse_unknown(name, raw, TOP)
    model_fields = [f.name for f in fields(ODMOConfig)]
    train_fields = [f.name for f in fields(TrainConfig)]
    model, train = _table(f"{name} [model]", raw.get("model", {})), _table(f"{name} [train]", raw.get("train", {}))
    refuse_unknown(f"{name} [model]", model, [k for k in model_fields if k not in DATA_SHAPES])
    refuse_unknown(f"{name} [train]", train, [k for k in train_fields if k not in ("seed", "epochs")])
    phases = []
    raw_phases = raw.get("phases")
    if not isinstance(raw_phases, list) or not raw_phases:
        raise UserError(f"{name}: a recipe needs at least one [[phases]] table")
    for i, p in enumerate(raw_phases):
        where = f"{name} phase {i + 1}"
        p = _table(where, p)
        refuse_unknown(where, p, [*PHASE, *(k for k in train_fields if k not in RUN_ONLY)])
        if "epochs" not in p:
            raise UserError(f"{where}: give its epochs")
        pm = _table(f"{where} [phases.model]", p.get("model", {}))
        refuse_unknown(f"{where} [phases.model]", pm, PHASE_MODEL)
        phases.append(Phase(str(p.get("name", f"phase {i + 1}")), {k: v for k, v in p.items() if k not in PHASE}, pm))
    from odmo_cli.models.odmo import PRESETS

    preset = str(raw.get("preset", "odmo"))
    if preset not in PRESETS:
        raise UserError(f"{name}: unknown preset {preset!r}; valid: {', '.join(PRESETS)}")
    recipe = Recipe(str(path), raw.get("dataset"), preset, model, train, phases, raw.get("budget_hours"))
    for i in range(len(phases)):  # every phase's configs are built once here, so errors come before training
        try:
            recipe.train_config(i)
            ODMOConfig(**{"skeleton": "humanact12", **recipe.model_values(i)})  # values only; the data's shapes come later
        except (TypeError, ValueError, UserError) as e:
            raise UserError(f"{name} phase {i + 1}: {e}") from None
    return recipe


def train_recipe(clips, recipe: Recipe, out: str | Path, *, seed: int = 0, threads: int = 0,
                 resume: Path | None = None, progress=None, device: str = "cpu"):
    """Train ODMO on clips with the recipe's phases in one run (or resume such a run's checkpoint),
    then write the final checkpoint with its bank, mode mixtures and report (training.odmo.finish), the
    report with the run's hours and pairs seen. `progress` gets every epoch's log with "epoch" counted
    over all phases."""
    from odmo_cli.checkpoint import load_checkpoint
    from odmo_cli.parallel import thread_count
    from odmo_cli.training.distributed import training_group
    from odmo_cli.training.loop import TrainResult
    from odmo_cli.training.odmo import ODMOTrainer, finish, model_config_for

    start, ckpt = 0, None
    if resume is not None:
        ckpt = load_checkpoint(resume)
        if "recipe" not in ckpt or "rng" not in ckpt:
            raise UserError(f"cannot resume {resume} with --recipe: it is not a recipe run's training checkpoint")
        if not same_training(Recipe.from_dict(ckpt["recipe"]), recipe):
            raise UserError(f"{resume} was trained with another recipe than {Path(recipe.source).name}; "
                            "resume it with the recipe it was started with")
        if int(ckpt["train_config"]["seed"]) != seed:
            raise UserError(f"{resume} was trained with --seed {ckpt['train_config']['seed']}, not {seed}")
        start = int(ckpt["recipe_phase"])

    def configs(i: int):
        tc = recipe.train_config(i, seed)
        return model_config_for(clips, recipe.model_values(i), recipe.preset), replace(tc, threads=threads or tc.threads)

    cfg, tc = configs(start)
    with thread_count(tc.threads), training_group(device) as group:
        trainer = ODMOTrainer(clips, cfg, tc, out, group)
        trainer.recipe, trainer.phase = recipe, start
        if ckpt is not None:
            trainer.load_state(ckpt)
            trainer._saved_epoch = trainer.epoch if Path(resume).resolve() == Path(out).resolve() else None
        for i in range(start, len(recipe.phases)):
            if i > start:
                trainer.enter_phase(i, *configs(i))
            offset = sum(p.train["epochs"] for p in recipe.phases[:i])
            trainer.run(None if progress is None else (lambda log, o=offset: progress({**log, "epoch": log["epoch"] + o})))
        seconds = sum(h.get("seconds", 0.0) for h in trainer.history)
        pairs = sum((recipe.train_config(i, seed).pairs_per_epoch or len(trainer.train_idx)) * p.train["epochs"]
                    for i, p in enumerate(recipe.phases))
        report = finish(trainer, {"hours": seconds / 3600, "pairs": pairs})
        return TrainResult(Path(out), recipe.epochs, trainer.history, report)
