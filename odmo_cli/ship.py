"""The models that ship in odmo_cli/assets/models: one recipe per dataset, rebuilt by one command.

`odmo ship humanact12 --out DIR` trains the evaluation classifier and ODMO with the recipe below,
fits the mode mixtures, and writes the compact files `sample`/`eval` load by short name (their
names: checkpoint.SHIPPED). The same seed gives the same files on one host (across hosts, kernels
may round differently). Each training checkpoint is kept beside them while it runs, so an
interrupted build continues where it stopped (resume is exact) instead of starting over.

Compact means: no optimizer, RNG or split, the loss history cut to its last entry, and the weights
stored as float16 (loaded back into float32 parameters). Most of ODMO's weights are the trajectory
generator's expand layer, (C*D + 3) x T(C*D + 3): 3.5 M of HumanAct12's 4.6 M values in the authors'
architecture. Matrices that large are stored as int8 with one float32 scale per row (symmetric,
|w| / 127 steps); `checkpoint.float_state` restores float32. Rounding that layer leaves the evaluation's
figures where they were, while int8 for every matrix costs about a point of Acc (the autoregressive decoder
amplifies the rounding), so only the large ones are rounded (docs/results.md, "The compact files").
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Callable


from odmo_cli.checkpoint import SHIPPED, compact, compact_classifier, load_checkpoint, save_checkpoint
from odmo_cli.data.locate import resolve
from odmo_cli.data.manifest import canonical_name
from odmo_cli.data.readers import read_dataset
from odmo_cli.errors import UserError
from odmo_cli.training.classifier import ClassifierTrainConfig, train_classifier
from odmo_cli.training.odmo import TrainConfig, train_odmo

# The recipes (docs/training.md, "The shipped models' recipes"): per dataset, the classifier's settings and
# ODMO's stages in order. Each stage after the first starts from the previous stage's compact file with a
# fresh optimizer and its own schedule; "model" holds the ODMOConfig values it changes on top of that file,
# "seed_offset" what it adds to the build's seed. Each stage was kept by a rule on the validation split set
# before it ran; what it was measured against, and why, is in docs/lab/ (one page per stage group).
# Classifier settings are those of the measured classifier runs (docs/lab/classifier.md).
_FREE_STAGE = {"epochs": 100, "lr": 3e-4, "lr_final": 3e-4, "tf_start": 0.0, "tf_end": 0.0, "tf_epochs": 1,
               "free_from": 0, "threads": 2}
_DECAYED_STAGE = {**_FREE_STAGE, "epochs": 150, "lr_final": 3e-5}
# "model": ODMOConfig values this stage changes (on top of the file it starts from)
_WEAK_ENERGY_STAGE = {**_DECAYED_STAGE, "epochs": 110, "batch_size": 64,
                      "model": {"energy_weight": 0.3, "free_energy_weight": 0.3}}
_LONG_STAGE = {**_WEAK_ENERGY_STAGE, "lr": 3e-3, "epochs": 330}
# the pose decoder alone, its position loss about the root (the encoder and the root paths stay the previous stage's)
_BODY_DECODER_STAGE = {**_LONG_STAGE, "train_parts": "motion", "model": {**_LONG_STAGE["model"], "pose_loss": "body"}}
# that stage with the decoder widened to 256 units (the paper's is 128), 300 epochs, at the build's seed + 2
_WIDE_DECODER_STAGE = {**_BODY_DECODER_STAGE, "epochs": 300, "seed_offset": 2,
                       "model": {**_BODY_DECODER_STAGE["model"], "motion_hidden": 256}}
# "seed_offset": this stage trains with the build's seed plus it
_HEIGHT_STAGE = {"epochs": 40, "lr": 1e-4, "lr_final": 1e-4, "tf_start": 0.3, "tf_end": 0.3, "tf_epochs": 1,
                 "free_from": 0, "val_every": 5, "train_parts": "trajectory", "threads": 2, "seed_offset": 3,
                 "model": {"height_weight": 3.0}}
# the pose decoder alone ("motion"): the codes and the root paths stay the previous stage's
_DECODER_STAGE = {**_DECAYED_STAGE, "epochs": 330, "lr": 1e-3, "batch_size": 64, "val_every": 10,
                  "train_parts": "motion"}
_FAST_DECODER_STAGE = {**_DECODER_STAGE, "lr": 3e-3}
RECIPES = {
    "humanact12": {
        "odmo": {"epochs": 1000, "lr": 3e-3, "lr_final": 1e-4, "tf_epochs": 500, "threads": 2},
        "odmo_stage2": _FREE_STAGE,
        "odmo_stage3": _DECAYED_STAGE,
        "odmo_stage4": _DECAYED_STAGE,
        "odmo_stage5": _WEAK_ENERGY_STAGE,
        "odmo_stage6": {**_LONG_STAGE, "epochs": 660, "seed_offset": 1},
        "odmo_stage7": {**_LONG_STAGE, "seed_offset": 1},
        "odmo_stage8": _WIDE_DECODER_STAGE,
        "odmo_stage9": _WIDE_DECODER_STAGE,
        "classifier": {"epochs": 200, "speed": 1.0, "threads": 1},
    },
    "cmu_mocap": {
        "odmo": {"epochs": 650, "lr": 3e-3, "lr_final": 1e-4, "tf_epochs": 325, "threads": 2},
        "odmo_stage2": _HEIGHT_STAGE,
        "odmo_stage3": _DECODER_STAGE,
        **{f"odmo_stage{n}": _FAST_DECODER_STAGE for n in (4, 5)},
        "odmo_stage6": {**_FAST_DECODER_STAGE, "epochs": 200, "crops": "first", "model": {"pose_loss": "body"}},
        "classifier": {"epochs": 100, "speed": 1.0, "threads": 1},
    },
}
def recipe_name(dataset: str) -> str:
    name = canonical_name(dataset)
    if name not in RECIPES:
        raise UserError(f"no shipping recipe for {dataset!r}; valid: {', '.join(RECIPES)}, cmu")
    return name


_LATER_STAGE = re.compile(r"odmo_stage(\d+)")


def _stages(recipe: dict) -> list[str]:
    """The recipe's ODMO stages in training order: "odmo", then "odmo_stage2", "odmo_stage3", ..."""
    numbers = sorted(int(m[1]) for k in recipe if (m := _LATER_STAGE.fullmatch(k)))
    if numbers != list(range(2, len(numbers) + 2)):
        raise ValueError(f"recipe stages must be odmo_stage2, odmo_stage3, ... in order, got stages {numbers}")
    return ["odmo", *(f"odmo_stage{n}" for n in numbers)] if "odmo" in recipe else []


def total_epochs(name: str) -> int:
    """ODMO epochs of a recipe, all stages together."""
    return sum(RECIPES[name][k]["epochs"] for k in _stages(RECIPES[name]))


def classifier_epochs(name: str) -> int:
    """The classifier's epochs in a dataset's recipe."""
    return RECIPES[name]["classifier"]["epochs"]


def build(dataset: str, data, out_dir: Path, seed: int = 0, skip_classifier: bool = False,
          progress: Callable | None = None, say: Callable[[str], None] = print, recipe_file: Path | None = None,
          classifier_progress: Callable | None = None) -> dict:
    """Train and write the shipped files for `dataset` into out_dir; returns both training reports
    (ODMO's: its last stage's). `progress` counts ODMO's epochs over all stages, `classifier_progress`
    the classifier's (each gets every epoch's log). `recipe_file`: ODMO is trained in one run of that
    recipe file's phases (training.recipe) instead of the stages below."""
    name = recipe_name(dataset)
    manifest, root = resolve(name, data)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"--out {out_dir} is a file; give a folder (it is made if missing)")
    out_dir.mkdir(parents=True, exist_ok=True)
    recipe, files = RECIPES[name], SHIPPED[name]
    clips = read_dataset(root, manifest)
    reports = {}
    if not skip_classifier:
        say(f"training the {manifest.name} classifier ({classifier_epochs(name)} epochs)")
        tc = ClassifierTrainConfig.from_dict({**recipe["classifier"], "seed": seed})
        work = out_dir / (Path(files["classifier"]).stem + ".training.pt")
        reports["classifier"] = train_classifier(clips, tc, work, resume=work if work.is_file() else None,
                                                 progress=classifier_progress).report
        save_checkpoint(out_dir / files["classifier"], compact_classifier(load_checkpoint(work)))
        work.unlink()
    if recipe_file is not None:
        reports["odmo"] = _odmo_recipe(clips, recipe_file, out_dir / files["odmo"], seed, progress, say)
    else:
        reports["odmo"] = _odmo_stages(clips, recipe, out_dir / files["odmo"], seed, progress, say)
    return reports


def _odmo_recipe(clips, path: Path, final: Path, seed: int, progress: Callable | None,
                 say: Callable[[str], None]) -> dict:
    """Train ODMO with a recipe file's phases into `final`'s training file beside it (resumed when it is
    there: a run of another recipe or seed is refused), then write the compact file; the run's report."""
    from odmo_cli.training.recipe import load_recipe, train_recipe

    plan = load_recipe(path)
    work = final.parent / f"{final.stem}.training.pt"
    resume = work if work.is_file() else None
    say(f"training ODMO on {clips.manifest.name} with {Path(path).name} ({len(plan.phases)} phases, {plan.epochs} epochs"
        f"{', resuming ' + str(work) if resume else ''})")
    result = train_recipe(clips, plan, work, seed=seed, resume=resume, progress=progress)
    save_checkpoint(final, compact(load_checkpoint(work)))
    work.unlink()
    return {"epochs": result.epochs, **result.report}


def stage_settings(stage: dict, seed: int) -> dict:
    """The TrainConfig values of a recipe stage in a build with `seed` (its seed_offset applied)."""
    settings = {k: v for k, v in stage.items() if k not in ("model", "seed_offset")}
    return {**settings, "seed": seed + stage.get("seed_offset", 0)}


def stage_differences(train_config: dict, config: dict | None, stage: dict, seed: int) -> list[str]:
    """How a stage's recorded training config and model config differ from the recipe's stage in a build
    with `seed` ("lr 0.001, not 0.003"); `config` None: not recorded (an older file's init chain
    lacks it), so its model values are not compared. Threads are not compared: they change
    the speed, not the run."""
    wanted = {k: v for k, v in stage_settings(stage, seed).items() if k != "threads"}
    differ = [f"{k} {train_config.get(k)!r}, not {v!r}" for k, v in wanted.items() if train_config.get(k) != v]
    if config is not None:
        differ += [f"{k} {config.get(k)!r}, not {v!r}" for k, v in stage.get("model", {}).items() if config.get(k) != v]
    return differ


def _check_settings(path: Path, stage: dict, seed: int) -> None:
    """A UserError when a stage file beside the output, finished or to be resumed, was trained with
    other settings or model values than the recipe's stage (a build under an older recipe or another
    --seed): the build would go on from the wrong weights, or resume would keep the file's own
    settings (training.loop: Trainer.resumed)."""
    ckpt = load_checkpoint(path)
    differ = stage_differences(ckpt.get("train_config", {}), ckpt.get("config", {}), stage, seed)
    if differ:
        raise UserError(f"{path} was trained with other settings than this recipe's stage ({'; '.join(differ)}); "
                        "remove it to train that stage again, or build into another --out folder")


def _odmo_stages(clips, recipe: dict, final: Path, seed: int, progress: Callable | None,
                 say: Callable[[str], None]) -> dict:
    """Train ODMO's stages into `final` (each later stage starts from the previous one's compact
    file, written beside it and removed at the end); returns the last stage's report."""
    out_dir = final.parent
    keys = _stages(recipe)
    start, offset, report = None, 0, {}  # the file the next stage starts from; epochs before it (the bar)
    for i, key in enumerate(keys):  # a stage finished by an earlier, interrupted build is not redone
        done = final if i == len(keys) - 1 else out_dir / f"{final.stem}.stage{i + 1}.pt"
        work = out_dir / (f"{final.stem}.training.pt" if i == 0 else f"{final.stem}.stage{i + 1}.training.pt")
        stage_progress = progress if not (progress and offset) else (
            lambda log, o=offset: progress({**log, "epoch": log["epoch"] + o}))
        if done != final and done.is_file() and not work.is_file():
            _check_settings(done, recipe[key], seed)
            start, offset = done, offset + recipe[key]["epochs"]
            continue
        resume = work if work.is_file() else None
        if resume:
            _check_settings(work, recipe[key], seed)
        tc = TrainConfig(**stage_settings(recipe[key], seed))
        say(f"training ODMO on {clips.manifest.name}{f', stage {i + 1}' if i else ''} ({tc.epochs} epochs"
            f"{', resuming ' + str(work) if resume else ''})")
        result = train_odmo(clips, tc, work, init=None if resume else start, overrides=recipe[key].get("model"),
                            resume=resume, progress=stage_progress)
        save_checkpoint(done, compact(load_checkpoint(work)))
        work.unlink()
        report = {"epochs": result.epochs, **result.report, "train_config": tc.to_dict()}
        start, offset = done, offset + tc.epochs
    for i in range(1, len(keys)):
        (out_dir / f"{final.stem}.stage{i}.pt").unlink(missing_ok=True)
    return report
