"""The models that ship in odmo_cli/assets/models: one recipe per dataset, rebuilt by one command.

`odmo ship humanact12 --out DIR` trains the evaluation classifier and ODMO with the recipe below,
fits the mode mixtures, and writes the compact files `sample`/`eval` load by short name. The
same seed gives the same files. ODMO's training checkpoint is kept beside them while it runs, so an
interrupted build continues where it stopped (resume is exact) instead of starting over.

Compact means: no optimizer, RNG or split, the loss history cut to its last entry, and the weights
stored as float16 (loaded back into float32 parameters). Most of ODMO's weights are the trajectory
generator's expand layer, (C*D + 3) x T(C*D + 3): 3.5 M values for HumanAct12 in the authors'
architecture, so float16 halves the file without changing the model.
"""

from __future__ import annotations

from dataclasses import asdict
from importlib import resources
from pathlib import Path
from typing import Callable

from odmo_cli.data.manifest import canonical_name
from odmo_cli.errors import UserError
from odmo_cli.io import load_checkpoint, save_checkpoint

# The CPU recipes (README "Shipped models"): cosine-decayed Adam from a higher rate than the paper's
# constant 1e-3, teacher forcing decayed over the first half; 2 threads. Classifier settings are
# those of the measured classifier runs (README "Evaluating").
RECIPES = {
    "humanact12": {
        "odmo": {"epochs": 1000, "lr": 3e-3, "lr_final": 1e-4, "tf_epochs": 500, "threads": 2},
        "classifier": {"epochs": 200, "speed": 2.0, "threads": 1},
        "file": "odmo_humanact12.pt", "classifier_file": "classifier_humanact12.pt",
    },
    "cmu_mocap": {
        "odmo": {"epochs": 650, "lr": 3e-3, "lr_final": 1e-4, "tf_epochs": 325, "threads": 2},
        "classifier": {"epochs": 100, "speed": 1.3, "threads": 1},
        "file": "odmo_cmu.pt", "classifier_file": "classifier_cmu.pt",
    },
}
_KEEP = ("format_version", "kind", "config", "train_config", "dataset", "epoch", "latent_bank", "modes", "report")


def compact(ckpt: dict) -> dict:
    """A finished checkpoint without what only training needs, weights as float16."""
    out = {k: ckpt[k] for k in _KEEP if k in ckpt}
    out["state_dict"] = {k: v.half() if v.is_floating_point() else v for k, v in ckpt["state_dict"].items()}
    out["history"] = list(ckpt.get("history", []))[-1:]
    out["weights_dtype"] = "float16"
    return out


def shipped_file(dataset: str, key: str = "file") -> Path | None:
    """The installed shipped file of a dataset (key "file": ODMO, "classifier_file"); None if absent."""
    recipe = RECIPES.get(canonical_name(dataset))
    if recipe is None:
        return None
    path = Path(str(resources.files("odmo_cli") / "assets" / "models" / recipe[key]))
    return path if path.is_file() else None


def recipe_name(dataset: str) -> str:
    name = canonical_name(dataset)
    if name not in RECIPES:
        raise UserError(f"no shipping recipe for {dataset!r}; valid: {', '.join(RECIPES)}, cmu")
    return name


def build(dataset: str, data, out_dir: Path, seed: int = 0, skip_classifier: bool = False,
          progress: Callable | None = None, say: Callable[[str], None] = print) -> dict:
    """Train and write the shipped files for `dataset` into out_dir; returns both training reports."""
    from odmo_cli.data.locate import resolve
    from odmo_cli.data.readers import read_dataset
    from odmo_cli.models.classifier import ClassifierTrainConfig, train_classifier
    from odmo_cli.train import TrainConfig, train_odmo

    name = recipe_name(dataset)
    manifest, root = resolve(name, data)
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise UserError(f"output folder {out_dir} does not exist")
    recipe = RECIPES[name]
    clips = read_dataset(root, manifest)
    reports = {}
    if not skip_classifier:
        say(f"training the {manifest.name} classifier ({recipe['classifier']['epochs']} epochs)")
        tc = ClassifierTrainConfig.from_dict({**recipe["classifier"], "seed": seed})
        reports["classifier"] = train_classifier(clips, tc, out_dir / recipe["classifier_file"])
    work = out_dir / (Path(recipe["file"]).stem + ".training.pt")
    resume = work if work.is_file() else None
    tc = TrainConfig(**{**recipe["odmo"], "seed": seed})
    say(f"training ODMO on {manifest.name} ({tc.epochs} epochs{', resuming ' + str(work) if resume else ''})")
    result = train_odmo(clips, tc, work, resume=resume, progress=progress)
    save_checkpoint(out_dir / recipe["file"], compact(load_checkpoint(work)))
    work.unlink()
    reports["odmo"] = {"epochs": result.epochs, **result.report, "train_config": asdict(tc)}
    return reports
