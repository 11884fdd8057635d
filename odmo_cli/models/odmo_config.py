"""ODMO's config: its sizes, losses and readouts (models.odmo builds the networks from it), and the
loss-scale presets `odmo train` starts from. Kept free of torch so the command line can build its
options from it without loading torch.
"""

from __future__ import annotations

from dataclasses import dataclass

from odmo_cli.config import Config, ConfigError, check_finite, knob
from odmo_cli.geometry.skeletons import SKELETONS

ROOTS = ("trajectory", "decoder", "ground")  # ODMOConfig.root
POSE_FRAMES = ("world", "path")  # ODMOConfig.pose_frame
POSE_LOSSES = ("world", "body")  # ODMOConfig.pose_loss
BONES = ("rigid", "free")  # ODMOConfig.bones
CONS = ("all", "ground")  # ODMOConfig.cons
ENERGY_ON = ("decoder", "drawn")  # ODMOConfig.energy_on


@dataclass
class ODMOConfig(Config):
    # the data's shapes (training.loop.dataset_shapes): set by the dataset, never by a user
    n_joints: int = 24
    n_classes: int = 12
    length: int = 60  # T
    up_axis: int = 1  # index of the vertical axis, weighted by up_weight in L_r and L_mre
    skeleton: str = ""  # geometry.skeletons' name: the feet of L_foot, the bones of L_bone and `bones`
    latent_dim: int = knob(20, "Size D of the latent code (paper 20).", "architecture")
    encoder_hidden: int = knob(64, "Hidden units of the LMP encoder (paper 64).", "architecture")
    encoder_fc: int = knob(256, "Units of the LMP encoder's fully connected layer (paper 256).", "architecture")
    traj_hidden: int = knob(128, "Hidden units of the trajectory generator (paper 128).", "architecture")
    motion_hidden: int = knob(128, "Hidden units of the pose decoder (paper 128); with --init, more than the file's "
                                   "widens its decoder, drawing the same motions at first.", "architecture")
    use_end_point: bool = True  # False trains the paper's -r_e variant (--ablate end-point)
    # losses (eq. 5) and their switches for the ablations -L_es, -L_traj, -L_cons (--ablate)
    alpha: float = knob(5.0, "Contrastive margin of L_es (paper 5).", "losses")
    sigma2: float = knob(0.05, "Prior variance of the code posterior (eq. 1; paper 0.05, release 0.0025; "
                               "default: the preset's).", "losses")
    same_class_deadzone: float = knob(0.25, "Dead zone of L_es for same-action pairs, relu(d^2 - it) (release 0.25).",
                                      "losses")
    # each term here is a mean over clips; the authors' release sums the two clips of a pair (as eq. 5
    # reads for a pair), which is 2
    recon_weight: float = knob(1.0, "Weight of L_r, L_mre and L_cons against L_es (paper 1: means over clips; "
                                    "release 2: summed over each pair; default: the preset's).", "losses")
    use_es: bool = True
    use_traj: bool = True
    use_cons: bool = True
    up_weight: float = knob(5.0, "Weight of the vertical coordinate in L_r and L_mre (release 5 on HumanAct12, "
                                 "1 on CMU MoCap; default: the preset's).", "losses")
    # velocities spread the end point's error over T tiny terms, and the model learns to ignore r_e
    traj_loss: str = knob("position", "What L_r compares: position (root positions, the release's) or velocity "
                                      "(per-step velocities, the paper's eq. 2).", "experimental")
    # position errors alone let the free-running decoder drift to an average, slow pose; velocity
    # errors weight the fast parts of a motion that drift loses
    vel_weight: float = knob(0.0, "Weight of L_vel, the squared error of frame-to-frame joint velocities "
                                  "(0: off, as in the paper and the release).", "experimental")
    # squared position errors reward a decoder that hedges between phases with a slow, small average
    # motion; this term does not
    energy_weight: float = knob(0.0, "Weight of L_energy, each joint's speed and amplitude about the root against "
                                     "the clip's (0: off, as in the paper and the release; default: the preset's).",
                                "losses")
    # teacher-forced steps move like the data; the free-running decoder is what drifts to a slow average
    free_energy_weight: float = knob(0.0, "Weight of L_energy on a second, free-running decode of the same codes, "
                                          "as sampling runs it, from --free-from on (0: off; default: the preset's).",
                                     "losses")
    # with rigid bones the decoder's stretch is motion that the readout takes away again
    energy_on: str = knob("decoder", "What the L_energy terms measure: decoder (the pose decoder's joints as it "
                                     "draws them) or drawn (the motion as decode reads it out, its bones as "
                                     "`bones` says).", "losses")
    # squared position errors flatten a jump's rise wherever its frame is uncertain; this term does not
    height_weight: float = knob(0.0, "Weight of L_height, the root height's speed and amplitude against the clip's, "
                                     "on the root sampling draws (0: off, as in the paper and the release).", "losses")
    # squared position errors straighten a path whose sway is uncertain in phase: a glide
    ground_weight: float = knob(0.0, "Weight of L_ground, the root path's travel on the ground plane (its mean step, "
                                     "sway and turns included) against the clip's, on the path sampling draws (0: off, "
                                     "as in the paper and the release).", "losses")
    # sampling draws codes between the training clips'; the other terms only see codes next to them
    mix_energy_weight: float = knob(0.0, "Weight of L_energy on free-running decodes of codes mixed between two "
                                         "training clips of one action, asked to move as that mixture of the two "
                                         "clips (0: off).", "experimental")
    # "trajectory" places the body on the path the end point conditions (docs/generation.md)
    root: str = knob("trajectory", "Where a decoded motion's root comes from: decoder (the pose decoder's own, the "
                                   "paper's), trajectory (the trajectory generator's path) or ground (that path on "
                                   "the ground plane, the pose decoder's height).", "architecture")
    pose_frame: str = knob("world", "What the pose decoder draws from: world (the dataset's frame, the paper's) or "
                                    "path (each frame's point of the generated trajectory).", "experimental")
    # with the root on the trajectory, CMU MoCap's world-frame loss is mostly the decoder's own path
    pose_loss: str = knob("world", "What L_mre compares: world (every joint in the dataset's frame, the paper's) or "
                                   "body (the joints about the root, the root's path once).", "losses")
    # a BVH's bones are rigid; the decoders of the paper and the release let bones stretch
    bones: str = knob("rigid", "What decode does with the bones: rigid (each bone its median length, the pelvis and "
                               "chest one shape; geometry.lie.rigid_bones) or free (the joints as drawn).",
                      "architecture")
    # the body and the path come from two networks; nothing else asks a planted foot's motion about the
    # root to cancel the root's travel
    foot_weight: float = knob(0.0, "Weight of L_foot, the slide of the feet of the motion sampling draws wherever "
                                   "the real clip's foot is planted (0: off, as in the paper and the release).",
                              "losses")
    foot_axes: str = knob("ground", "What L_foot holds still: the slide on the ground plane, or all three axes.",
                          "losses")
    # the cause of stretching limbs, where `bones = "rigid"` mends the output after it
    bone_weight: float = knob(0.0, "Weight of L_bone, each bone of the pose decoder's output against the clip's "
                                   "length for it (0: off).", "experimental")
    # the decoder sees the previous poses, where the trajectory generator draws the whole path at once
    cons: str = knob("all", "What L_cons ties to the trajectory: all (the pose decoder's root, the paper's) or "
                            "ground (its path on the ground plane, leaving the height to the decoder).", "losses")

    def __post_init__(self):
        check_finite(self)
        choices = {"traj_loss": ("position", "velocity"), "root": ROOTS, "pose_frame": POSE_FRAMES,
                   "pose_loss": POSE_LOSSES, "bones": BONES, "cons": CONS, "foot_axes": ("ground", "all"),
                   "energy_on": ENERGY_ON}
        for name, valid in choices.items():
            if getattr(self, name) not in valid:
                raise ConfigError(name, f"must be one of {', '.join(valid)}, got {getattr(self, name)!r}")
        if self.skeleton and self.skeleton not in SKELETONS:
            raise ConfigError("skeleton", f"must be one of {', '.join(SKELETONS)}, got {self.skeleton!r}")
        for name in ("sigma2", "recon_weight"):
            if not getattr(self, name) > 0:
                raise ConfigError(name, f"must be a number > 0, got {getattr(self, name)}")
        for name in ("vel_weight", "energy_weight", "free_energy_weight", "height_weight", "mix_energy_weight",
                     "foot_weight", "bone_weight", "ground_weight"):
            if getattr(self, name) < 0:
                raise ConfigError(name, f"must be a number >= 0, got {getattr(self, name)}")
        for name in ("foot_weight", "bone_weight"):
            if getattr(self, name) and not self.skeleton:
                raise ConfigError(name, "needs the skeleton (its feet and bones): set skeleton")
        if self.energy_on == "drawn" and not self.skeleton:
            raise ConfigError("energy_on", "drawn needs the skeleton (the bones decode reads out): set skeleton")
        for name in ("latent_dim", "encoder_hidden", "encoder_fc", "traj_hidden", "motion_hidden"):
            if getattr(self, name) < 1:
                raise ConfigError(name, f"must be a positive number of units, got {getattr(self, name)}")


# The loss scales `odmo train` and `odmo ship` use, per dataset: value and source. ODMOConfig's own
# defaults are the paper's text where it speaks (sigma2 = 0.05 as a variance, each clip's terms
# averaged); "paper" keeps them. "release" is the authors' code (param_humanact12.py, param_mocap.py,
# param_uestc.py, trainer.py). "odmo", the default, is the release plus the two L_energy terms, without
# which the sampled motion is damped (docs/training.md, "Presets"; the measurements: docs/lab/damping.md).
_RELEASE_SIGMA = (0.0025, "release: the prior is Normal(0, 0.05) with 0.05 a standard deviation")
_RELEASE_RECON = (2.0, "release: the two clips' reconstruction terms of a pair are summed")
PRESETS: dict[str, dict[str, dict[str, tuple[float, str]]]] = {
    "paper": {},
    "release": {
        "humanact12": {"sigma2": _RELEASE_SIGMA, "recon_weight": _RELEASE_RECON,
                       "up_weight": (5.0, "release: y_weights = 5 (param_humanact12.py)")},
        "cmu_mocap": {"sigma2": _RELEASE_SIGMA, "recon_weight": _RELEASE_RECON,
                      "up_weight": (1.0, "release: y_weights = 1 (param_mocap.py)")},
        "uestc": {"sigma2": _RELEASE_SIGMA, "recon_weight": _RELEASE_RECON,
                  "up_weight": (5.0, "release: y_weights = 5 (param_uestc.py)")},
        "*": {"sigma2": _RELEASE_SIGMA, "recon_weight": _RELEASE_RECON},  # any other dataset
    },
}
_ENERGY = (2.0, "odmo: squared position errors alone damp the decoder's motion; this term asks for the real "
                "clip's speed and amplitude (docs/lab/damping.md)")
_FREE = (2.0, "odmo: the same on a free-running decode, as sampling runs the decoder, where the damping "
               "shows (docs/lab/damping.md)")
PRESETS["odmo"] = {name: {**row, "energy_weight": _ENERGY, "free_energy_weight": _FREE}
                   for name, row in PRESETS["release"].items()}


def preset_values(preset: str, dataset: str) -> dict[str, float]:
    """The ODMOConfig values of a preset for a dataset (its own row, else the preset's "*" row)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; valid: {', '.join(PRESETS)}")
    rows = PRESETS[preset]
    return {k: v for k, (v, _) in rows.get(dataset, rows.get("*", {})).items()}
