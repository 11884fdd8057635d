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
|w| / 127 steps); `checkpoint.float_state` restores float32. Measured on the shipped HumanAct12 model (full
protocol, 10 x 250; the file shipped on 2026-12-01): int8 rows for the expand layer leave Acc and FID unchanged (90.06 / 0.592 against
90.06 / 0.593), while int8 for every matrix costs 1 point of Acc and raises FID to 0.764 (the
autoregressive decoder amplifies the rounding), so only the large ones are rounded.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Callable

import torch

from odmo_cli.checkpoint import SHIPPED, load_checkpoint, save_checkpoint
from odmo_cli.data.locate import resolve
from odmo_cli.data.manifest import canonical_name
from odmo_cli.data.readers import read_dataset
from odmo_cli.errors import UserError
from odmo_cli.training.classifier import ClassifierTrainConfig, train_classifier
from odmo_cli.training.odmo import TrainConfig, train_odmo

# The CPU recipes (docs/training.md): cosine-decayed Adam from a higher rate than the paper's
# constant 1e-3, teacher forcing decayed over the first half; 2 threads. On HumanAct12 then a second
# stage from the first stage's compact file: 100 epochs without teacher forcing (the decoder trained
# as it samples), constant rate 3e-4, a fresh optimizer (on CMU MoCap the same stage measured worse),
# then twice, each from the previous stage's compact file, 150 more such epochs with the rate decayed
# 3e-4 -> 3e-5 (stages 3 and 4: each lowered the validation error and read better under both classifiers),
# then 110 such epochs at batch 64 with L_energy and its free-running twin at 0.3 instead of 2 (stage 5:
# the lowest validation error of five continuations whose validation speed and amplitude stay within
# the quality bars), then that stage at the rate 3e-3 -> 3e-5 for 660 epochs and for 330, each
# from the previous stage's compact file, at the build's seed + 1 (stages 6 and 7, of "the E line at seed 1":
# kept by a rule on the validation split written before they ran, which they met; they replaced sixteen
# stages 6-21 that took 0.71 M pairs more: docs/training.md), then twice 300 epochs training the pose decoder
# alone, widened to 256 units, with its position loss about the root, at the build's seed + 2 (stages 8 and
# 9, "S8H": they replaced a third E stage and one such stage, kept by the rule for decoder-only stages set
# before they ran: the training clips' body at least 10% under the one stage's, the validation split's at most
# 2% over; docs/training.md).
# On CMU MoCap one later stage: 40 epochs with L_height (weight 3) on the trajectory generator's root,
# training that network only (the encoder and pose decoder stay stage 1's), teacher forcing held at 0.3,
# constant rate 1e-4, the build's seed + 3 (`seed_offset`: the seeds run before its rule was set are not
# candidates; seed 3 was the first run of this shape under it, and met it on the validation split:
# docs/results.md); then 330 epochs of the pose decoder alone at batch 64 without teacher forcing, the
# rate decayed 1e-3 -> 3e-5, the preset's L_energy (stage 3: its decoder had had 2.6 k steps where the
# release trains over 20 k; kept by a rule on the validation split's body error about the root); then
# that stage twice more at 3e-3 -> 3e-5 (stages 4 and 5, kept together by a rule set before they ran: the
# body error on the training clips 10% under stage 3's, the validation split's no worse than 2% over it);
# then 200 epochs of that stage on each training clip's first crop, with the pose loss about the root
# (stage 6, "CF6B": the crops sampling draws its codes from, and a loss that leaves their root paths to
# the trajectory generator; kept by a rule on the validation split's body error set before it ran).
# Classifier settings are those of the measured classifier runs (docs/evaluation.md).
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
_KEEP = ("format_version", "kind", "config", "train_config", "dataset", "epoch", "latent_bank", "crop_bank", "modes", "report",
         "init", "recipe", "recipe_phase")


INT8_MIN_VALUES = 1 << 20  # matrices with at least this many values are stored as int8 rows


def compact(ckpt: dict, int8_min_values: int = INT8_MIN_VALUES) -> dict:
    """A finished checkpoint without what only training needs: weights as float16, and matrices of
    at least `int8_min_values` values as int8 rows with a float32 scale each."""
    out = {k: ckpt[k] for k in _KEEP if k in ckpt}
    state, scales = {}, {}
    for k, v in ckpt["state_dict"].items():
        if v.is_floating_point() and v.dim() == 2 and v.numel() >= int8_min_values:
            state[k], scales[k] = int8_rows(v)
        else:
            state[k] = v.half() if v.is_floating_point() else v
    out["state_dict"] = state
    out["int8_scales"] = scales
    out["history"] = list(ckpt.get("history", []))[-1:]
    out["weights_dtype"] = "float16" + (f"; int8 rows for {', '.join(scales)}" if scales else "")
    return out


def int8_rows(w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(R, K) float -> (R, K) int8 and (R, 1) float32 scales with w ~= q * scale, |q| <= 127.

    The scales stay float32 (R values): in float16 the floor that keeps an all-zero row from
    dividing by zero would underflow to 0.
    """
    w = w.float()
    scale = (w.abs().amax(dim=1, keepdim=True) / 127).clamp_min(1e-12)
    q = torch.round(w / scale).clamp(-127, 127).to(torch.int8)
    return q, scale


def recipe_name(dataset: str) -> str:
    name = canonical_name(dataset)
    if name not in RECIPES:
        raise UserError(f"no shipping recipe for {dataset!r}; valid: {', '.join(RECIPES)}, cmu")
    return name


def compact_classifier(ckpt: dict) -> dict:
    """A finished classifier checkpoint without its optimizer and RNG state; weights stay float32
    (evaluation numbers must not move) and the split stays (`odmo eval --held-out` reads it)."""
    return {k: v for k, v in ckpt.items() if k not in ("optimizer", "rng")}


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


def build(dataset: str, data, out_dir: Path, seed: int = 0, skip_classifier: bool = False,
          progress: Callable | None = None, say: Callable[[str], None] = print, recipe_file: Path | None = None) -> dict:
    """Train and write the shipped files for `dataset` into out_dir; returns both training reports
    (ODMO's: its last stage's). `progress` counts ODMO's epochs over all stages. `recipe_file`: ODMO is
    trained in one run of that recipe file's phases (training.recipe) instead of the stages below."""
    name = recipe_name(dataset)
    manifest, root = resolve(name, data)
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise UserError(f"output folder {out_dir} does not exist")
    recipe, files = RECIPES[name], SHIPPED[name]
    clips = read_dataset(root, manifest)
    reports = {}
    if not skip_classifier:
        say(f"training the {manifest.name} classifier ({recipe['classifier']['epochs']} epochs)")
        tc = ClassifierTrainConfig.from_dict({**recipe["classifier"], "seed": seed})
        work = out_dir / (Path(files["classifier"]).stem + ".training.pt")
        reports["classifier"] = train_classifier(clips, tc, work, resume=work if work.is_file() else None)
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
    result = train_recipe(clips, plan, work, seed, resume, progress)
    save_checkpoint(final, compact(load_checkpoint(work)))
    work.unlink()
    return {"epochs": result.epochs, **result.report}


def stage_settings(stage: dict, seed: int) -> dict:
    """The TrainConfig values of a recipe stage in a build with `seed` (its seed_offset applied)."""
    settings = {k: v for k, v in stage.items() if k not in ("model", "seed_offset")}
    return {**settings, "seed": seed + stage.get("seed_offset", 0)}


def stage_differences(train_config: dict, config: dict | None, stage: dict, seed: int) -> list[str]:
    """How a stage's recorded training config and model config differ from the recipe's stage in a build
    with `seed` ("lr 0.001, not 0.003"); `config` None: not recorded (a stage before 2026-12-06 in a
    file's init chain), so its model values are not compared. Threads are not compared: they change
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
        result = train_odmo(clips, tc, work, recipe[key].get("model"), resume=resume, progress=stage_progress,
                            init=None if resume else start)
        save_checkpoint(done, compact(load_checkpoint(work)))
        work.unlink()
        report = {"epochs": result.epochs, **result.report, "train_config": tc.to_dict()}
        start, offset = done, offset + tc.epochs
    for i in range(1, len(keys)):
        (out_dir / f"{final.stem}.stage{i}.pt").unlink(missing_ok=True)
    return report
