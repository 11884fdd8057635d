"""ODMO's loss terms (main paper eq. 1-5). Each returns one value per sequence or pair, (B,).

The paper writes squared norms; the authors' release averages over coordinates and weights the
vertical coordinate x5, which sets the balance between reconstruction and the contrastive term
that produced the paper's numbers. We follow the release's scale (up_weight in the config).
Our terms are means over clips; the release sums a pair's two clips, which is recon_weight = 2.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from odmo_cli.geometry.kinematics import bone_lengths, root_velocities
from odmo_cli.geometry.skeletons import SKELETONS, ground_axes
from odmo_cli.measures.plausibility import CONTACT_HEIGHT  # the evaluation's contact, so the loss and the measure agree
from odmo_cli.models.odmo import read_out


def contrastive(mu1: torch.Tensor, mu2: torch.Tensor, same: torch.Tensor, alpha: float,
                deadzone: float = 0.25) -> torch.Tensor:
    """Spring energy of code pairs (B, D): same class relu(d^2 - deadzone), else relu(alpha - d)^2.

    The factor 1/2 is the springs' energy 1/2 k x^2 (supplement §3.2).
    """
    d2 = (mu1 - mu2).pow(2).sum(-1)  # (B,)
    d = torch.sqrt(d2 + 1e-9)
    pull = F.relu(d2 - deadzone)
    push = F.relu(alpha - d).pow(2)
    return 0.5 * torch.where(same, pull, push)


def variance_prior(logvar: torch.Tensor, sigma2: float) -> torch.Tensor:
    """KL(N(0, diag s^2) || N(0, sigma2 I)) per row of logvar (B, D): the -ln det S + tr(S)/sigma2
    term of eq. 1, with the constants that make it zero at s^2 = sigma2."""
    return 0.5 * (logvar.exp() / sigma2 - 1.0 - logvar + math.log(sigma2)).sum(-1)


def standard_kl(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """KL(N(mu, diag s^2) || N(0, I)) per row (B, D) -> (B,): the classic VAE term."""
    return 0.5 * (mu.pow(2) + logvar.exp() - 1.0 - logvar).sum(-1)


def coordinate_weights(up_axis: int, up_weight: float, device=None) -> torch.Tensor:
    w = torch.ones(3, device=device)
    w[up_axis] = up_weight
    return w


def sequence_error(pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Sum over time of the (weighted) mean squared coordinate error: (B, T, ..., 3) -> (B,)."""
    err = (pred - target).pow(2)
    if weights is not None:
        err = err * weights
    return err.flatten(2).mean(-1).sum(-1)


def about_root(motion: torch.Tensor) -> torch.Tensor:
    """(B, T, J, 3) -> (B, T, J, 3): the root as it is, every other joint measured from the root."""
    return torch.cat([motion[:, :, :1], motion[:, :, 1:] - motion[:, :, :1]], dim=2)


def _smooth(x: torch.Tensor, k: int) -> torch.Tensor:
    """A centred k-frame moving average over axis 1 (the frames): (B, T, ...) -> (B, T - k + 1, ...)."""
    return x.unfold(1, k, 1).mean(-1) if k > 1 else x


def body_motion_stats(motion: torch.Tensor, smooth: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """Per clip and joint: speed (mean norm of the frame-to-frame change) and amplitude (RMS distance
    from the mean position) of the joints about the root, after a `smooth`-frame moving average:
    (B, T, J, 3) -> (B, J-1), (B, J-1). The differentiable twin of diagnostics.body_speed/body_amplitude."""
    body = motion[:, :, 1:] - motion[:, :, :1]  # (B, T, J-1, 3)
    body = _smooth(body, smooth)  # (B, T - smooth + 1, J-1, 3)
    speed = torch.sqrt(body.diff(dim=1).pow(2).sum(-1) + 1e-12).mean(1)
    amplitude = torch.sqrt((body - body.mean(1, keepdim=True)).pow(2).sum(-1).mean(1) + 1e-12)
    return speed, amplitude


def energy_error(pred: torch.Tensor, target: torch.Tensor, floor: float = 0.005) -> torch.Tensor:
    """How far a motion's speed and amplitude about the root are from its target's, relative to the
    target's (phase-blind: it asks for as much motion, not for the same frames): (B,).

    Each joint's error is divided by the target clip's mean over joints, floored at `floor` (units
    per frame, or units) so that clips that hardly move do not dominate."""
    return _stats_error(body_motion_stats(pred), body_motion_stats(target), floor)


def mixed_energy_error(pred: torch.Tensor, first: torch.Tensor, second: torch.Tensor, lam: torch.Tensor,
                       floor: float = 0.005) -> torch.Tensor:
    """energy_error of pred (B, T, J, 3) against the lam-weighted mean (lam: (B,)) of two clips' speeds and
    amplitudes, joint by joint: a decode of the code lam z1 + (1 - lam) z2 asked to move as much as the
    clips it lies between, in whatever phase: (B,)."""
    (s1, a1), (s2, a2) = body_motion_stats(first), body_motion_stats(second)
    w = lam[:, None]
    return _stats_error(body_motion_stats(pred), (w * s1 + (1 - w) * s2, w * a1 + (1 - w) * a2), floor)


def _stats_error(pred_stats, target_stats, floor: float) -> torch.Tensor:
    (sp, ap), (st, at) = pred_stats, target_stats
    ns = st.mean(1, keepdim=True).clamp_min(floor)
    na = at.mean(1, keepdim=True).clamp_min(floor)
    return (((sp - st) / ns).pow(2) + ((ap - at) / na).pow(2)).mean(1)


def root_height_stats(motion: torch.Tensor, up_axis: int, smooth: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """Per clip: speed (mean absolute frame-to-frame change) and amplitude (standard deviation about
    its least-squares line over time) of the root's height, after a `smooth`-frame moving average:
    (B, T, J, 3) -> (B,), (B,). A steady climb or sink is no amplitude: a decoder could otherwise
    match a jump's spread by drifting (measured: it did). The twin of
    diagnostics.root_height_speed_and_amplitude."""
    h = motion[:, :, 0, up_axis]  # (B, T)
    h = _smooth(h, smooth)  # (B, T - smooth + 1)
    speed = h.diff(dim=1).abs().mean(1)
    t = torch.arange(h.shape[1], dtype=h.dtype, device=h.device)
    t = t - t.mean()
    hc = h - h.mean(1, keepdim=True)
    resid = hc - (hc @ t / t.pow(2).sum())[:, None] * t  # (B, T'), the line removed
    amplitude = torch.sqrt(resid.pow(2).mean(1) + 1e-12)
    return speed, amplitude


def height_error(pred: torch.Tensor, target: torch.Tensor, up_axis: int, speed_floor: float = 0.002,
                 amplitude_floor: float = 0.01) -> torch.Tensor:
    """How far the root height's speed and amplitude are from the target clip's, phase-blind, as
    squared log ratios: (B,). The floors (units per frame, units) are added to both sides.

    The body about the root cannot show a jump; the root's rise and fall does, and squared position
    errors flatten it wherever the takeoff's frame is uncertain. Log ratios, not energy_error's relative
    errors: a root that hardly moves (a 5 mm bob) would otherwise weigh a hundred times a jump's
    (measured: the relative form flattened every action's height on CMU MoCap, jumps included)."""
    (sp, ap), (st, at) = root_height_stats(pred, up_axis), root_height_stats(target, up_axis)
    return (torch.log((sp + speed_floor) / (st + speed_floor)).pow(2)
            + torch.log((ap + amplitude_floor) / (at + amplitude_floor)).pow(2))



def ground_speed(path: torch.Tensor, up_axis: int, smooth: int = 3) -> torch.Tensor:
    """Per clip: the mean length of the frame-to-frame step of a path (B, T, 3) on the ground plane,
    after a `smooth`-frame moving average: (B,), units per frame: how far the root travels, its sway
    and turns included, not only from its first point to its last."""
    g = _smooth(path[..., list(ground_axes(up_axis))], smooth)  # (B, T - smooth + 1, 2)
    return torch.sqrt(g.diff(dim=1).pow(2).sum(-1) + 1e-12).mean(1)


def ground_error(path: torch.Tensor, target: torch.Tensor, up_axis: int, floor: float = 0.002) -> torch.Tensor:
    """How far a root path's (B, T, 3) travel on the ground plane (ground_speed) is from the target clip's
    (B, T, J, 3) root's, phase-blind, as a squared log ratio with `floor` (units per frame) added to both
    sides: (B,). Squared position errors straighten a path whose sway and turns are uncertain in phase,
    and the path that is left covers the distance at a glide (as height_error for the root's rise)."""
    sp, st = ground_speed(path, up_axis), ground_speed(target[:, :, 0], up_axis)
    return torch.log((sp + floor) / (st + floor)).pow(2)


def contact_labels(motion: torch.Tensor, feet: list[int], leg: tuple[int, int, int], up_axis: int,
                   up_sign: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each foot joint of real clips (B, T, J, 3) stays planted: (B, T-1, F) bool, true for a step
    in which the joint is within CONTACT_HEIGHT leg lengths of its lowest point in the clip at both
    frames (the evaluation's contact, plausibility.foot_contacts, with each clip's own mean leg length
    where the evaluation takes the dataset's median), and the clips' leg lengths (B,)."""
    hip, knee, ankle = leg
    length = ((motion[:, :, hip] - motion[:, :, knee]).norm(dim=-1)
              + (motion[:, :, knee] - motion[:, :, ankle]).norm(dim=-1)).mean(1)  # (B,)
    h = up_sign * motion[:, :, feet, up_axis]  # (B, T, F)
    planted = h - h.amin(1, keepdim=True) < CONTACT_HEIGHT * length[:, None, None]
    return planted[:, 1:] & planted[:, :-1], length


def foot_contact_error(pred: torch.Tensor, target: torch.Tensor, feet: list[int], leg: tuple[int, int, int],
                       up_axis: int, up_sign: float, vertical: bool = False) -> torch.Tensor:
    """How far pred's (B, T, J, 3) foot joints slide on the ground plane (with `vertical`, move at all)
    where the target clip's are planted (contact_labels): the squared frame-to-frame displacement in leg
    lengths, summed over the planted steps and averaged over the frames: (B,). 0 for feet that stay where
    the clip's stay. A planted foot that keeps its height too ties the root's height to the legs' bend."""
    planted, length = contact_labels(target, feet, leg, up_axis, up_sign)
    axes = [0, 1, 2] if vertical else list(ground_axes(up_axis))
    step = pred[:, 1:, feet][..., axes] - pred[:, :-1, feet][..., axes]  # (B, T-1, F, 2 or 3)
    slide = step.pow(2).sum(-1) / length[:, None, None].pow(2)
    return (slide * planted).sum(dim=(1, 2)) / planted.shape[1]


def bone_length_error(pred: torch.Tensor, target: torch.Tensor, parents, leg: tuple[int, int, int]) -> torch.Tensor:
    """How far each bone of pred (B, T, J, 3) is from the target clip's length for it (its median over the
    clip's frames), squared, in leg lengths, averaged over bones and frames: (B,). 0 for a body of the
    clip's size that keeps it; what a decoder of joint positions otherwise lets stretch."""
    child = [j for j, p in enumerate(parents) if p >= 0]
    pred_len = bone_lengths(pred, parents)  # (B, T, J-1)
    real_len = bone_lengths(target, parents).median(dim=1).values  # (B, J-1)
    hip, knee, ankle = leg
    length = real_len[:, child.index(knee)] + real_len[:, child.index(ankle)]  # (B,): hip-knee and knee-ankle bones
    return ((pred_len - real_len[:, None]) / length[:, None, None]).pow(2).mean(dim=(1, 2))


def drawn_motion(out: dict, cfg) -> torch.Tensor:
    """The motion (B, T, J, 3) sampling draws of this batch: the free-running decode when there is one,
    else the teacher-forced, read out as ODMO.decode reads it (its root and bones as cfg says)."""
    return read_out(out.get("free_motion", out["motion"]), out["trajectory"], cfg)


def energy_view(decoded: torch.Tensor, trajectory: torch.Tensor, cfg) -> torch.Tensor:
    """The motion (B, T, J, 3) the L_energy terms measure: the pose decoder's joints as it draws them, or
    with cfg.energy_on "drawn" as decode reads them out. The terms are taken about the root, so of the
    readout only the bones count: rigid bones take away the motion a decoder puts into stretching them."""
    return read_out(decoded, trajectory, cfg) if cfg.energy_on == "drawn" else decoded


def drawn_path(out: dict, cfg) -> torch.Tensor:
    """The root path (B, T, 3) whose ground-plane coordinates sampling draws: the trajectory generator's,
    or with cfg.root "decoder" the pose decoder's root on its free-running decode when there is one."""
    if cfg.root == "decoder":
        return out.get("free_motion", out["motion"])[:, :, 0]
    return out["trajectory"]


def drawn_root(out: dict, cfg) -> torch.Tensor:
    """The root whose height sampling draws, (B, T, 1, 3): the trajectory generator's with cfg.root
    "trajectory", else the pose decoder's on its free-running decode when there is one (the decode
    that sampling runs)."""
    if cfg.root == "trajectory":
        return out["trajectory"][:, :, None]
    return out.get("free_motion", out["motion"])[:, :, :1]


def odmo_terms(out: dict, motion: torch.Tensor, labels: torch.Tensor, cfg) -> dict[str, torch.Tensor]:
    """All loss terms for a batch whose first half is paired index-wise with its second half.

    out: the model's forward on motion (2B, T, J, 3) with labels (2B,). Returns batch means.
    """
    w = coordinate_weights(cfg.up_axis, cfg.up_weight, motion.device)
    real_traj = motion[:, :, 0]  # (2B, T, 3)
    if cfg.traj_loss == "velocity":  # the paper's eq. 2
        l_r = sequence_error(root_velocities(out["trajectory"]), root_velocities(real_traj), w)
    else:  # the release: positions
        l_r = sequence_error(out["trajectory"], real_traj, w)
    if cfg.pose_loss == "body":  # the root's path counts once, not in every joint
        l_mre = sequence_error(about_root(out["motion"]), about_root(motion), w)
    else:
        l_mre = sequence_error(out["motion"], motion, w)
    if cfg.cons == "ground":  # the path on the ground plane only: the decoder's root height is its own
        # (the mean over two axes, not three: each ground axis weighs 1.5 times what it does with "all",
        # as measured in docs/lab/planted-feet.md)
        ground = list(ground_axes(cfg.up_axis))
        l_cons = sequence_error(out["trajectory"][..., ground], out["motion"][:, :, 0, ground])
    else:
        l_cons = sequence_error(out["trajectory"], out["motion"][:, :, 0])
    l_vel = sequence_error(out["motion"].diff(dim=1), motion.diff(dim=1), w)
    l_energy = (energy_error(energy_view(out["motion"], out["trajectory"], cfg), motion) if cfg.energy_weight
                else motion.new_zeros(len(motion)))
    l_free = (energy_error(energy_view(out["free_motion"], out["trajectory"], cfg), motion) if "free_motion" in out
              else motion.new_zeros(len(motion)))
    l_height = (height_error(drawn_root(out, cfg), motion, cfg.up_axis) if cfg.height_weight
                else motion.new_zeros(len(motion)))
    l_ground = (ground_error(drawn_path(out, cfg), motion, cfg.up_axis) if cfg.ground_weight
                else motion.new_zeros(len(motion)))
    sk = SKELETONS.get(cfg.skeleton)  # the feet and bones of L_foot and L_bone (the config requires one for them)
    l_foot = (foot_contact_error(drawn_motion(out, cfg), motion, list(sk.feet), sk.legs[0][:3], cfg.up_axis,
                                 sk.up_sign, vertical=cfg.foot_axes == "all")
              if cfg.foot_weight and sk else motion.new_zeros(len(motion)))
    l_bone = (bone_length_error(out.get("free_motion", out["motion"]), motion, sk.parents, sk.legs[0][:3])
              if cfg.bone_weight and sk else motion.new_zeros(len(motion)))
    half = len(motion) // 2
    l_mix = motion.new_zeros(half)  # per pair; 0 for pairs of two actions, which are not mixed
    if "mix_motion" in out:
        rows = out["mix_rows"]
        mixed = energy_view(out["mix_motion"], out["mix_trajectory"], cfg)
        l_mix = l_mix.index_put((rows,), mixed_energy_error(mixed, motion[:half][rows],
                                                            motion[half:][rows], out["mix_lam"][rows]))
    mu, logvar = out["mu"], out["logvar"]
    same = labels[:half] == labels[half:]
    l_con = contrastive(mu[:half], mu[half:], same, cfg.alpha, cfg.same_class_deadzone)
    l_prior = variance_prior(logvar, cfg.sigma2)
    return {
        "es": l_con.mean() + l_prior.mean() * 2,  # eq. 1: the prior on both codes of each pair
        "r": l_r.mean(),
        "mre": l_mre.mean(),
        "cons": l_cons.mean(),
        "vel": l_vel.mean(),
        "energy": l_energy.mean(),
        "free_energy": l_free.mean(),
        "height": l_height.mean(),
        "ground": l_ground.mean(),
        "mix_energy": l_mix.mean(),
        "foot": l_foot.mean(),
        "bone": l_bone.mean(),
        "vae": standard_kl(mu, logvar).mean() * 2,
    }


def total_loss(terms: dict[str, torch.Tensor], cfg) -> torch.Tensor:
    """Eq. 5 with the ablation switches. Without L_es, ODMO "becomes a classic VAE" (§4.2.4):
    the contrastive and sigma2 terms are replaced by the KL to N(0, I)."""
    recon = terms["mre"]
    if cfg.vel_weight:
        recon = recon + cfg.vel_weight * terms["vel"]
    if cfg.energy_weight:
        recon = recon + cfg.energy_weight * terms["energy"]
    if cfg.free_energy_weight:
        recon = recon + cfg.free_energy_weight * terms["free_energy"]
    if cfg.height_weight:
        recon = recon + cfg.height_weight * terms["height"]
    if cfg.ground_weight:
        recon = recon + cfg.ground_weight * terms["ground"]
    if cfg.mix_energy_weight:
        recon = recon + cfg.mix_energy_weight * terms["mix_energy"]
    if cfg.foot_weight:
        recon = recon + cfg.foot_weight * terms["foot"]
    if cfg.bone_weight:
        recon = recon + cfg.bone_weight * terms["bone"]
    if cfg.use_traj:
        recon = recon + terms["r"]
    if cfg.use_cons:
        recon = recon + terms["cons"]
    return cfg.recon_weight * recon + (terms["es"] if cfg.use_es else terms["vae"])
