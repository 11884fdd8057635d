"""Loading an evaluation classifier: an odmo classifier checkpoint (kind "classifier", written by
`odmo train classifier`), an Action2Motion release file (a torch file holding a dict whose `model`
entry is the state dict; see `A2M_RELEASES`, checked by SHA-256), or a bare state dict with the
same names. All are loaded with `torch.load(weights_only=True)`.
"""

from __future__ import annotations

import hashlib
import warnings
from pathlib import Path

import numpy as np
import torch

from odmo_cli.checkpoint import load_checkpoint
from odmo_cli.errors import UserError
from odmo_cli.models.classifier import ClassifierConfig, MotionClassifier

# The classifiers released with Action2Motion (Guo et al., 2020), by file name. ODMO evaluates
# HumanAct12 with the released one; for CMU MoCap it drops Wash (7 classes) and trains its own.
A2M_RELEASES: dict[str, dict] = {
    "action_recognition_model_humanact12.tar": {
        "sha256": "e2d231fd8a425bc642d4c342466d5eaae2ae16e8a67e8dd253820ef5512d7bca",
        "dataset": "humanact12", "n_classes": 12, "input_size": 72, "hidden": 128, "layers": 2,
        "note": "classes in the order of the coarse action codes 01..12 (the humanact12 manifest's order)",
    },
    "action_recognition_model_mocap_new.tar": {
        "sha256": "7ef619637e61934a57254642021d065adf8afd59f56be7c39f205eea064aa154",
        "dataset": "cmu_mocap", "n_classes": 8, "input_size": 60, "hidden": 128, "layers": 2,
        "note": "8 classes including Wash, which ODMO drops: scored on ODMO's 7 by name (the Wash logit is left out)",
        # its label order (Action2Motion's label_enc_rev_mocap.txt), as manifest action names
        "classes": ["walk", "wash", "run", "jump", "animal_behavior", "dance", "step", "climb"],
    },
}


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def config_from_state_dict(state: dict, source: str = "state dict") -> ClassifierConfig:
    """Infer input size, hidden units, layers, feature size and classes from the tensor shapes."""
    need = ["recurrent.weight_ih_l0", "recurrent.weight_hh_l0", "linear1.weight", "linear2.weight"]
    missing = [k for k in need if k not in state]
    if missing:
        raise UserError(f"{source} is not a motion classifier: missing {', '.join(missing)} "
                        "(expected recurrent.*, linear1.*, linear2.* as in Action2Motion)")
    try:
        w_ih, w_hh = state["recurrent.weight_ih_l0"], state["recurrent.weight_hh_l0"]
        hidden = int(w_hh.shape[1])
        layers = 0
        while f"recurrent.weight_ih_l{layers}" in state:
            layers += 1
        feature, n_classes = int(state["linear1.weight"].shape[0]), int(state["linear2.weight"].shape[0])
        ok = (w_ih.dim() == 2 and w_ih.shape[0] == 3 * hidden and tuple(w_hh.shape) == (3 * hidden, hidden)
              and tuple(state["linear1.weight"].shape) == (feature, hidden)
              and tuple(state["linear2.weight"].shape) == (n_classes, feature))
    except (AttributeError, IndexError, TypeError):
        ok = False
    if not ok:
        raise UserError(f"{source}: tensor shapes are not those of a GRU classifier")
    return ClassifierConfig(input_size=int(w_ih.shape[1]), n_classes=n_classes, hidden=hidden,
                            layers=layers, feature=feature)


def _strip_prefix(state: dict) -> dict:
    """Drop a DataParallel `module.` prefix if every key has it."""
    if state and all(isinstance(k, str) and k.startswith("module.") for k in state):
        return {k[len("module."):]: v for k, v in state.items()}
    return dict(state)


def _is_state_dict(obj) -> bool:
    return isinstance(obj, dict) and bool(obj) and all(torch.is_tensor(v) for v in obj.values())


def load_classifier(path: str | Path, expect_classes: int | None = None, expect_input: int | None = None,
                    expect_actions: list[str] | tuple[str, ...] | None = None) -> MotionClassifier:
    """A classifier in eval mode from an odmo checkpoint or an Action2Motion release file.

    expect_input (J*3) and expect_classes are checked against the weights; a mismatch is a
    UserError naming both sides. expect_actions is checked against the action names an odmo
    checkpoint records (A2M files record none). The returned model's `info` says where it came
    from: `source` ("odmo", "a2m" or "state_dict"), `sha256`, `release` (the A2M release file the
    hash matches, or None), `verified` (hash matches a known release; None for odmo checkpoints),
    `dataset` (the dataset description, when known). An A2M file named like a release whose hash
    differs triggers a warning.
    """
    path = Path(path)
    payload = load_checkpoint(path)  # weights_only=True; UserError for missing/unreadable files
    info: dict = {"file": str(path)}
    if "kind" in payload:
        if payload["kind"] != "classifier":
            raise UserError(f"{path} is a {payload['kind']!r} checkpoint, not a classifier "
                            "(train one with `odmo train classifier` or use an Action2Motion classifier file)")
        try:
            cfg = ClassifierConfig.from_saved(payload["config"])
            state = payload["state_dict"]
        except (KeyError, TypeError):
            raise UserError(f"{path}: classifier checkpoint without config or state_dict") from None
        info.update(source="odmo", dataset=payload.get("dataset", {}), report=payload.get("report", {}),
                    format_version=payload.get("format_version"), verified=None, release=None)
        if isinstance(payload.get("split"), dict):  # clip indices it was trained / validated on
            info["split"] = {k: np.asarray(v, dtype=np.int64) for k, v in payload["split"].items()}
    else:
        if "model" in payload and _is_state_dict(payload["model"]):
            state, source = _strip_prefix(payload["model"]), "a2m"
        elif _is_state_dict(payload):
            state, source = _strip_prefix(payload), "state_dict"
        else:
            raise UserError(f"{path} is neither an odmo classifier checkpoint nor an Action2Motion "
                            "classifier file (a dict with the state dict under 'model')")
        cfg = config_from_state_dict(state, str(path))
        digest = file_sha256(path)
        release = next((name for name, r in A2M_RELEASES.items() if r["sha256"] == digest), None)
        info.update(source=source, sha256=digest, release=release, verified=release is not None,
                    dataset={"name": A2M_RELEASES[release]["dataset"]} if release else {})
        if release is None and path.name in A2M_RELEASES:
            warnings.warn(f"{path.name}: SHA-256 {digest[:12]}... does not match the Action2Motion release "
                          f"({A2M_RELEASES[path.name]['sha256'][:12]}...); using its weights as they are",
                          stacklevel=2)
    _check_expectations(cfg, expect_classes, expect_input)
    actions = info.get("dataset", {}).get("actions")
    if expect_actions is not None and actions is not None and list(actions) != list(expect_actions):
        raise UserError(f"classifier was trained on actions {', '.join(actions)}; "
                        f"the dataset has {', '.join(expect_actions)}")
    model = MotionClassifier(cfg)
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[0]
        raise UserError(f"{path}: weights do not fit the classifier ({first})") from None
    model.info = info
    return model.eval()


def _check_expectations(cfg: ClassifierConfig, expect_classes: int | None, expect_input: int | None) -> None:
    if expect_input is not None and int(expect_input) != cfg.input_size:
        joints = f"{expect_input // 3} joints" if expect_input % 3 == 0 else f"{expect_input} inputs per frame"
        raise UserError(f"classifier expects {cfg.input_size} inputs ({cfg.n_joints} joints), "
                        f"the dataset has {joints}")
    if expect_classes is not None and int(expect_classes) != cfg.n_classes:
        raise UserError(f"classifier has {cfg.n_classes} classes, the dataset has {expect_classes} actions")


def check_matches(model: MotionClassifier, manifest) -> None:
    """UserError unless the classifier fits the dataset's skeleton and number of actions. An
    Action2Motion release whose classes include all of the dataset's (its MoCap file has Wash, which
    ODMO drops) is scored on those: its logits are taken in the dataset's action order."""
    release = A2M_RELEASES.get(model.info.get("release") or "", {})
    classes, actions = release.get("classes"), list(manifest.action_names)
    if classes and set(actions) <= set(classes) and len(classes) == model.cfg.n_classes:
        _check_expectations(model.cfg, None, 3 * manifest.skeleton.n_joints)
        model.keep = [classes.index(a) for a in actions]
        return
    _check_expectations(model.cfg, len(manifest.actions), 3 * manifest.skeleton.n_joints)
