"""Long motions: a sequence of actions as one continuous motion (`odmo compose`).

A spec names the segments in order, separated by commas (`parse_spec`):

    walk 4s, sit, drink#1 2s to 1.5,0.5

each an action of the model, then optionally `#MODE` (one of its discovered modes, `odmo modes`), a
duration (`4s`, or `80f` frames; default one model length) and `to X,Z`: the point of the ground plane
where the segment ends, in the composition's frame (its first root at the origin, the dataset's axes).

ODMO makes windows of T frames (its clip length). A composition is built window by window
(docs/generation.md, "Long motions"):

- The first window is an ordinary sample; or, with `start`, the given motion is kept exactly.
- Every later window is *primed* with the motion's last k frames so far (ComposeConfig.prime): the
  autoregressive pose decoder is teacher-forced with them for k steps, then draws the window's new
  frames (k + m steps for the m <= T frames kept), starting from the encoding of the path the
  trajectory generator drew for the window (T frames from the origin, as in training; without an end
  point the same encoding gives the heading below). The root path is theirs for those k steps and the
  trajectory generator's own after them, its ground-plane velocity fading in from the primer's over
  the transition (`seam.splice_path`).
- The window is drawn in the model's frame, as the model was trained: the primed frames are moved so
  their first root is at the origin and turned about the up axis so that the body faces, at the seam,
  where the model itself faces in its first frame for this code (one decoder step); the new frames are
  turned and moved back. So root position and heading carry on across the seam.
- The seam: the new frames carry the difference between the last primed pose and the decoder's own pose
  there, fading out (`seam.fade`), so the first new frame continues the last old one by the decoder's
  own step. The fade lasts the transition (ComposeConfig.blend frames), longer where the difference is
  large enough that no joint moves faster than fade_speed on its account; each ankle's share of it on
  the ground fades no faster than half the skating speed, the leg following by IK (`seam.settle_feet`),
  so that feet glide rather than skate into place.
- The root's height is the path's own above the composition's first root (a standing body's), so that a
  body that sat down stands up again in the next action instead of carrying its drop on.
- A segment longer than one window is continued by further windows of the same action, each with a
  fresh code of the same mode; a shorter one keeps the first frames. With `to X,Z` each window's end
  point is corrected (ComposeConfig.end_steps times) so that its last kept frame lands on its share of
  the way.
- A model with rigid bones (ODMOConfig.bones) gives every later window, once faded, the body of the first
  one (or of the given start): its bone lengths and its torso's shape (geometry.lie.rigid_bones), so the
  body keeps its size throughout and a BVH reproduces it.

`method="paste"` is the cut-and-paste baseline the measurements compare with (evaluation/composition.py):
every window sampled on its own, placed so its first root is on the last one's on the ground plane,
nothing primed or blended.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from odmo_cli.checkpoint import LoadedODMO, model_name
from odmo_cli.config import ConfigError
from odmo_cli.data.manifest import normalize_action
from odmo_cli.device import model_device
from odmo_cli.errors import UserError
from odmo_cli.formats.samples import write_samples
from odmo_cli.generation.generate import end_points_for
from odmo_cli.generation.seam import fade, fade_length, heading, leg_length, settle_feet, splice_path, turn, wrap
from odmo_cli.geometry.kinematics import bone_lengths
from odmo_cli.geometry.lie import rigid_bones, rigid_pieces, torso_branches
from odmo_cli.geometry.skeletons import get_skeleton, ground_axes
from odmo_cli.models.latent import codes_of, mode_ids
from odmo_cli.models.odmo import condition, read_out

METHODS = ("primed", "paste")
START_LABEL = "start"  # frame_actions of the frames a composition was started from
SPEC_HELP = "ACTION[#MODE] [DURATION] [to X,Z], comma-separated, e.g. 'walk 4s, sit, drink#1 2s to 1.5,0.5'"

_NUMBER = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)"
_SEGMENT = re.compile(
    r"(?P<action>[A-Za-z][\w\-]*(?:\s+[A-Za-z][\w\-]*)*?)"  # words, each starting with a letter
    r"(?:\s*\#\s*(?P<mode>\d+))?"
    rf"(?:\s+(?P<amount>{_NUMBER})\s*(?P<unit>s|f))?"
    rf"(?:\s+to\s+(?P<x>{_NUMBER})\s*,\s*(?P<z>{_NUMBER}))?")


@dataclass(frozen=True)
class Segment:
    """One segment of a spec, as written."""

    action: str
    mode: int | None = None
    seconds: float | None = None  # at most one of seconds and frames; neither: one model length
    frames: int | None = None
    end: tuple[float, float] | None = None  # a point of the ground plane (its two axes in order)
    text: str = ""


@dataclass
class ComposeConfig:
    """How windows are joined, in frames. The defaults were measured on both shipped models
    (docs/generation.md, "Long motions"): more primed frames keep more of the previous action in the
    decoder, and a longer transition more of it in the motion, both at the cost of the new action's
    accuracy; a shorter transition makes faster seams."""

    prime: int = 2  # k: frames of the motion so far teacher-forced into each new window (2 at least)
    blend: int = 6  # frames of the shortest fade: the transition, and the shortest segment
    fade_speed: float = 2.0  # leg lengths a second at most that a fade moves a joint by (0: always `blend`)
    longest: int = 20  # frames of the longest fade, and of the longest glide of a foot
    settle: bool = True  # feet glide into place at half the skating speed (seam.settle_feet)
    end_steps: int = 3  # corrections of a window's end point toward an asked point
    method: str = "primed"  # or "paste", the baseline

    def __post_init__(self):
        if self.method not in METHODS:
            raise ConfigError("method", f"must be one of {', '.join(METHODS)}; got {self.method!r}")
        for name, low in (("prime", 2), ("blend", 1), ("longest", self.blend), ("end_steps", 0), ("fade_speed", 0)):
            if getattr(self, name) < low:
                raise ConfigError(name, f"must be at least {low}; got {getattr(self, name)}")


def parse_spec(text: str) -> list[Segment]:
    """'walk 4s, sit, drink#1 2s to 1.5,0.5' -> segments; UserError naming the part it cannot read."""
    parts = [p.strip() for p in re.split(r",\s*(?=[A-Za-z])", text.strip())] if text.strip() else []
    if not parts:
        raise UserError(f"the spec is empty; write {SPEC_HELP}")
    segments = []
    for i, part in enumerate(parts, start=1):
        m = _SEGMENT.fullmatch(part)
        if m is None:
            raise UserError(f"cannot read segment {i}, {part!r}; write {SPEC_HELP}")
        amount, unit = m["amount"], m["unit"]
        seconds = frames = None
        if amount is not None:
            value = float(amount)
            if unit == "f" and value != int(value):
                raise UserError(f"segment {i}, {part!r}: a duration in frames is a whole number, got {amount}f")
            if value <= 0:
                raise UserError(f"segment {i}, {part!r}: the duration must be positive, got {amount}{unit}")
            seconds, frames = (value, None) if unit == "s" else (None, int(value))
        end = (float(m["x"]), float(m["z"])) if m["x"] is not None else None
        segments.append(Segment(m["action"].strip(), int(m["mode"]) if m["mode"] else None, seconds, frames, end, part))
    return segments


@dataclass(frozen=True)
class Planned:
    """A segment checked against the model: its action's index, frames and end point."""

    action: int
    name: str
    mode: int | None
    frames: int
    end: np.ndarray | None  # (3,) with NaN on the up axis


def plan(loaded: LoadedODMO, segments: list[Segment], cfg: ComposeConfig) -> list[Planned]:
    """Every segment's action, mode, length and end point, checked before any work (UserError)."""
    fps, T = loaded.dataset["fps"], loaded.model.cfg.length
    transition = cfg.blend
    up = get_skeleton(loaded.dataset["skeleton"]).up_index
    out = []
    for i, seg in enumerate(segments, start=1):
        where = f"segment {i}, {seg.text or seg.action!r}"
        key = normalize_action(seg.action)
        if key not in loaded.actions:
            raise UserError(f"unknown action {seg.action!r} in {where}; valid: {', '.join(loaded.actions)}")
        a = loaded.actions.index(key)
        k = len(loaded.action_modes(a).means)
        if seg.mode is not None and not 0 <= seg.mode < k:
            raise UserError(f"mode {seg.mode} in {where} is out of range: {key} has {k} modes (0..{k - 1})")
        frames = seg.frames if seg.frames is not None else (
            int(round(seg.seconds * fps)) if seg.seconds is not None else T)
        if frames < transition:
            raise UserError(f"{where} lasts {frames} frames ({frames / fps:g} s), shorter than the transition of "
                            f"{transition} frames ({transition / fps:g} s) that blends it with its neighbour; "
                            f"give at least {transition}f")
        end = None
        if seg.end is not None:
            if not loaded.model.cfg.use_end_point:
                raise UserError(f"{where} asks for an end point, but {Path(loaded.source).name} was trained without "
                                "end-point conditioning; drop its 'to X,Z'")
            end = np.full(3, np.nan, dtype=np.float32)
            end[list(ground_axes(up))] = seg.end
        out.append(Planned(a, key, seg.mode, frames, end))
    return out


@dataclass
class Composition:
    """K sequences of one spec, each L frames, and how they are cut into segments."""

    motions: np.ndarray  # (K, L, J, 3) float32, the dataset's frame; the first root at the origin
    frame_actions: np.ndarray  # (L,) str: each frame's action (START_LABEL for a given start)
    segments: np.ndarray  # (S, 2) int64: each segment's first frame and end (exclusive)
    segment_actions: np.ndarray  # (S,) str
    segment_modes: np.ndarray  # (K, S) int64: the mode each sequence's segment was drawn from
    segment_ends: np.ndarray  # (S, 3) float32: the asked end points, NaN where none (and on the up axis)
    yaw: np.ndarray  # (K, L) float32 radians: the turn about the up axis that placed each frame's window
    prefix_frames: int  # leading frames that are the given start, exactly
    dataset: dict
    model: str
    seed: int
    spec: str
    method: str

    def __len__(self) -> int:
        return len(self.motions)

    @property
    def title(self) -> str:
        """The sequence's actions joined by '+', e.g. 'walk+sit+drink' (its `actions` entry)."""
        return "+".join(str(a) for a in self.segment_actions)

    def reached(self) -> np.ndarray:
        """(K, S, 3): the root at each segment's last frame."""
        return self.motions[:, self.segments[:, 1] - 1, 0]

    def save(self, path: str | Path) -> None:
        """The samples file (docs/formats.md): one motion per sequence, plus the composition's keys."""
        K = len(self)
        last = self.segment_ends[-1]
        asked = np.isfinite(last)
        write_samples(path, self.motions, actions=np.full(K, self.title), modes=np.full(K, -1, dtype=np.int64),
                      codes=np.zeros((K, 0), dtype=np.float32), end_points=np.repeat(last[None], K, axis=0),
                      end_mask=np.repeat(asked[None], K, axis=0), dataset=self.dataset, model=model_name(self.model),
                      seed=self.seed, extra={
                          "frame_actions": self.frame_actions.astype(str), "segments": self.segments,
                          "segment_actions": self.segment_actions.astype(str), "segment_modes": self.segment_modes,
                          "segment_end_points": self.segment_ends, "prefix_frames": np.int64(self.prefix_frames),
                          "spec": np.str_(self.spec), "method": np.str_(self.method)})


# -- the windows ------------------------------------------------------------------------------------

class _Windows:
    """Decodes the windows of one composition: the model, its skeleton and the seam's lengths."""

    def __init__(self, loaded: LoadedODMO, cfg: ComposeConfig):
        self.model = loaded.model
        self.T = self.model.cfg.length
        self.sk = get_skeleton(loaded.dataset["skeleton"])
        self.up = self.sk.up_index
        self.g = list(ground_axes(self.up))
        self.cfg = cfg
        self.fps = float(loaded.dataset["fps"])
        self.dev = model_device(self.model)
        self.free_cfg = replace(self.model.cfg, bones="free")
        self.rigid = self.model.cfg.bones == "rigid" and bool(self.model.cfg.skeleton)
        self.branches = torso_branches(self.sk) if self.rigid else {}
        self.lengths: torch.Tensor | None = None  # (K, J): the composition's bones (rigid models), set by keep_body
        self.pieces: dict[int, torch.Tensor] | None = None  # its torso's rigid pieces (geometry.lie.rigid_pieces)

    def keep_body(self, motion: torch.Tensor) -> None:
        """Every later window's body is motion's (K, L, J, 3): each bone's median length, the torso's mean shape."""
        if self.rigid:
            parents = self.sk.parents
            child = [j for j, p in enumerate(parents) if p >= 0]
            self.lengths = motion.new_zeros(len(motion), len(parents))
            self.lengths[:, child] = bone_lengths(motion, parents).median(dim=-2).values
            self.pieces = rigid_pieces(motion, self.branches)

    def body(self, motion: torch.Tensor) -> torch.Tensor:
        """motion (K, T', J, 3) with the composition's body (`keep_body`): rigid models only."""
        return rigid_bones(motion, self.sk.parents, self.lengths, self.branches, self.pieces)

    def _cond(self, z: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        return condition(F.one_hot(labels, self.model.cfg.n_classes).to(z.dtype), z)  # (K, C*D)

    def _path(self, cond: torch.Tensor, end: torch.Tensor) -> torch.Tensor:
        return torch.cumsum(self.model.trajectory(cond, end), dim=1)  # (K, T, 3), r_t = sum of v

    def _decode(self, cond, path, primer=None, states=None, rigid=True, steps=None) -> torch.Tensor:
        """The pose decoder along `path` (K, T', 3), teacher-forced with primer (K, k, J, 3) at its
        first k frames -> its first `steps` frames (K, steps, J, 3; default all T'), the root read as the
        model's cfg.root says, the bones as its cfg.bones says (rigid: the composition's body, `keep_body`;
        rigid=False leaves them free for a caller that makes them rigid later). states: the decoder's
        starting state (MotionGenerator.encode_path), when not path's own. The decoder is causal, so with
        rigid=False (or the composition's body set) the frames drawn do not depend on `steps`: a window cut
        short is not drawn to its end."""
        motion_net = self.model.motion
        states = states if states is not None else motion_net.encode_path(path)
        prepared = (states, motion_net.step_inputs(cond, path.shape[1])[:steps])  # t/T' over the whole window
        path = path[:, :steps]
        T = path.shape[1]
        target = teacher = None
        if primer is not None:
            k = primer.shape[1]
            target = torch.cat([primer, primer.new_zeros(len(primer), T - k, *primer.shape[2:])], dim=1)
            teacher = torch.arange(T, device=path.device) <= k  # step t is fed target[t - 1]
        poses = self.model.poses(prepared, path, target, teacher)  # (K, T, J, 3)
        motion = read_out(poses, path, self.free_cfg)
        if self.rigid and rigid:
            motion = self.body(motion)
        return motion

    def _own_pose(self, cond, states) -> torch.Tensor:
        """The first pose the model draws for this code on its own (one step of the pose decoder from
        `states`, its path's encoding): (K, J, 3) in its frame, its root as the decoder draws it."""
        first_step = self.model.motion.step_inputs(cond, self.T)[:1]
        return self.model.motion.unroll((states, first_step))[:, 0].view(len(cond), -1, 3)

    def first(self, z, labels, ends, m: int, target: torch.Tensor | None):
        """The composition's first window: an ordinary sample from the origin -> (K, m, J, 3), drawn whole
        (a rigid model's body is that of all T frames) and cut."""
        cond = self._cond(z, labels)
        path, _ = self._aim(cond, ends, target, lambda p: p - p[:, :1], 1, m - 1)
        motion = self._decode(cond, path)
        return motion[:, :m] - motion[:, :1, :1]

    def primed(self, z, labels, ends, prev: torch.Tensor, m: int, target: torch.Tensor | None):
        """A window continuing prev (K, k, J, 3), the motion's last k frames (world frame) -> its m <= T
        new frames (K, m, J, 3) in the world frame and the turn that placed them (K,). The decoder runs
        k + m steps (the k primed ones, then the frames kept) from the encoding of the path the trajectory
        generator drew (T frames from the origin, as in training), not of the spliced path."""
        k = prev.shape[1]
        cond = self._cond(z, labels)
        raw = self._path(cond, ends)  # (K, T, 3)
        states = self.model.motion.encode_path(raw)
        own = self._own_pose(cond, states)
        yaw = wrap(heading(prev[:, -1], self.sk) - heading(own, self.sk))
        rot = turn(yaw, self.up)  # (K, 3, 3) model -> world
        anchor = prev[:, 0, 0]  # (K, 3)
        primer = torch.einsum("ktjc,kcd->ktjd", prev - anchor[:, None, None], rot)  # world -> model: x R
        height = -anchor[:, self.up]  # the composition's reference height (its first root's) in this frame
        if target is not None:
            target = torch.einsum("kc,kcd->kd", torch.nan_to_num(target - anchor), rot)
        after = lambda p: torch.cat([p[:, :1].expand(-1, k, -1), p], dim=1)  # noqa: E731  (K, k + T, 3)
        path, drawn = self._aim(cond, ends, target,
                                lambda p: splice_path(after(p), primer[:, :, 0], height, self.cfg.blend, self.up),
                                k, k + m - 1, raw)
        if target is not None:  # aimed at a target: the path was drawn again
            states = self.model.motion.encode_path(drawn)
        motion = self._decode(cond, path, primer, states, rigid=False, steps=k + m)  # (K, k + m, J, 3), bones free
        offset = primer[:, -1] - motion[:, k - 1]  # (K, J, 3); a rigid model's bones are made rigid after the fade
        cfg = self.cfg
        frames = cfg.blend
        if cfg.fade_speed and self.sk.legs:
            leg = leg_length(primer[:, -1], self.sk.legs[0])  # (K,)
            frames = fade_length(offset, cfg.blend, cfg.longest, cfg.fade_speed * leg / self.fps)  # (K,)
        own = motion[:, k:k + m]
        new = fade(own, offset, frames)
        if self.rigid:  # the decoder's bones, and the fade moving a bone's two ends apart: back to the body
            faded, new = new, self.body(new)
            own = new - (faded - own)  # the decoder's own frames as the body reads them: the fade's share out
        if cfg.settle:  # the leg's IK keeps the lengths
            new = settle_feet(new, own, offset, self.sk, self.fps, cfg.longest)
        return torch.einsum("ktjd,kcd->ktjc", new, rot) + anchor[:, None, None], yaw

    def _aim(self, cond, ends, target, place, first: int, last: int, raw=None) -> tuple[torch.Tensor, torch.Tensor]:
        """The window's placed path (K, T', 3) and the trajectory generator's path it was placed from
        (K, T, 3). With a target (K, 3) in its frame, the end point's ground
        coordinates start at the target's and are corrected end_steps times by the miss at frame `last`;
        what is still missed then is taken up by the path's ground-plane coordinates, growing linearly
        from frame `first` - 1 to `last`, so the path lands on the target (the trajectory generator
        reaches only end points like its training clips', and a point farther than the action goes in
        its time would be missed). raw: the path for `ends`, when already drawn."""
        if target is None:
            drawn = raw if raw is not None else self._path(cond, ends)
            return place(drawn), drawn
        ends = ends.clone()
        ends[:, self.g] = target[:, self.g]
        drawn = self._path(cond, ends)
        path = place(drawn)
        for _ in range(self.cfg.end_steps):
            ends[:, self.g] += target[:, self.g] - path[:, last, self.g]
            drawn = self._path(cond, ends)
            path = place(drawn)
        miss = target[:, self.g] - path[:, last, self.g]  # (K, 2)
        t = torch.arange(path.shape[1], dtype=path.dtype, device=path.device)
        share = ((t - first + 1) / (last - first + 1)).clamp(0, 1)  # (T',)
        path = path.clone()
        path[..., self.g] += share[None, :, None] * miss[:, None]
        return path, drawn

    def pasted(self, z, labels, ends, prev: torch.Tensor | None, m: int, target: torch.Tensor | None):
        """The baseline: a window sampled on its own (bones as the model decodes them; a target (K, 3) is
        its end point), its first root placed on prev's last (K, 1, J, 3) on the ground plane -> (K, m, J, 3)."""
        if target is not None:  # asked as `odmo sample --end` asks it: the window's end point
            start = prev[:, -1, 0] if prev is not None else torch.zeros_like(target)
            ends = ends.clone()
            ends[:, self.g] = (target - start)[:, self.g]
        _, motion = self.model.decode(z, labels, ends)
        motion = motion[:, :m] - motion[:, :1, :1]
        if prev is not None:
            shift = torch.zeros(len(motion), 3, dtype=motion.dtype, device=motion.device)
            shift[:, self.g] = prev[:, -1, 0, self.g]
            motion = motion + shift[:, None, None]
        return motion


# -- a composition ----------------------------------------------------------------------------------

def _tail(pieces: list[torch.Tensor], k: int) -> torch.Tensor | None:
    """The last k frames (K, k, J, 3) of the pieces (K, L_i, J, 3) joined (fewer if there are fewer)."""
    if not pieces:
        return None
    last, have = [], 0
    for piece in reversed(pieces):
        last.insert(0, piece[:, -(k - have):])
        have += last[0].shape[1]
        if have >= k:
            break
    return torch.cat(last, dim=1)


def _segment(win: _Windows, loaded: LoadedODMO, seg: Planned, ids: np.ndarray, rng: np.random.Generator,
             pieces: list[torch.Tensor], yaws: list[torch.Tensor]) -> None:
    """Append one segment's windows (K, m, J, 3) to `pieces` and their turns (K, m) to `yaws`: as many
    windows of at most T frames as its length takes, each a fresh code of the modes `ids` (K,)."""
    n, dev, method = len(ids), win.dev, win.cfg.method
    end = torch.from_numpy(seg.end).to(dev) if seg.end is not None else None
    left = seg.frames
    while left > 0:
        prev = _tail(pieces, win.cfg.prime)  # (K, k, J, 3), None before the first window
        m = min(left, win.T)
        target = None
        if end is not None:  # this window's share of the way to the segment's end
            here = prev[:, -1, 0] if prev is not None else torch.zeros(n, 3, device=dev)
            target = here + (end - here) * (m / left)
            target[:, win.up] = float("nan")
        z = codes_of(loaded.action_modes(seg.action), ids, rng)  # (K, D)
        ends = end_points_for(loaded, seg.action, z, None)  # (K, 3)
        z, ends = torch.from_numpy(z).to(dev), torch.from_numpy(ends).to(dev)
        lab = torch.full((n,), seg.action, dtype=torch.long, device=dev)
        yaw = torch.zeros(n, device=dev)
        if method == "paste":
            new = win.pasted(z, lab, ends, prev, m, target)
        elif prev is None:
            new = win.first(z, lab, ends, m, target)
        else:
            new, yaw = win.primed(z, lab, ends, prev, m, target)
        pieces.append(new)
        if win.lengths is None and method == "primed":
            win.keep_body(new)
        yaws.append(yaw[:, None].expand(-1, m))
        left -= m


@torch.inference_mode()
def compose(loaded: LoadedODMO, spec: str | list[Segment], n: int = 1, seed: int = 0,
            start: np.ndarray | None = None, cfg: ComposeConfig | None = None) -> Composition:
    """n sequences of the spec's segments, each one continuous motion (module docstring).

    start (L0, J, 3): a motion to continue, moved so its first root is at the origin and kept
    exactly as the first L0 frames. Every random choice (modes, codes) comes from `seed`.
    """
    cfg = cfg or ComposeConfig()
    if not isinstance(loaded, LoadedODMO):
        raise UserError(f"{loaded.source} is a {getattr(loaded, 'kind', '?')} model; composing needs an ODMO model "
                        "(its end points and its autoregressive pose decoder)")
    if n <= 0:
        raise UserError(f"--n must be a positive number of sequences, got {n}")
    segments = parse_spec(spec) if isinstance(spec, str) else list(spec)
    planned = plan(loaded, segments, cfg)
    J = loaded.model.cfg.n_joints
    if start is not None:
        start = _check_start(start, J, loaded)
    win = _Windows(loaded, cfg)
    rng = np.random.default_rng(seed)
    dev = win.dev
    pieces, yaws, labels_so_far = [], [], []
    if start is not None:
        given = torch.from_numpy(start - start[:1, :1]).to(dev)  # (L0, J, 3), first root at the origin
        pieces.append(given[None].expand(n, -1, -1, -1))
        win.keep_body(pieces[0])
        yaws.append(torch.zeros(n, len(start), device=dev))
        labels_so_far += [START_LABEL] * len(start)
    prefix = len(start) if start is not None else 0
    bounds, seg_modes = [], []
    for seg in planned:
        ids = mode_ids(loaded.action_modes(seg.action), n, rng, seg.mode).astype(np.int64)
        seg_modes.append(ids)
        first = sum(p.shape[1] for p in pieces)
        _segment(win, loaded, seg, ids, rng, pieces, yaws)
        bounds.append((first, first + seg.frames))
        labels_so_far += [seg.name] * seg.frames
    motions = torch.cat(pieces, dim=1)  # (K, L, J, 3)
    return Composition(
        motions.cpu().numpy().astype(np.float32), np.array(labels_so_far), np.array(bounds, dtype=np.int64),
        np.array([s.name for s in planned]), np.stack(seg_modes, axis=1),
        np.stack([s.end if s.end is not None else np.full(3, np.nan, np.float32) for s in planned]),
        torch.cat(yaws, dim=1).cpu().numpy().astype(np.float32), prefix, loaded.dataset, loaded.source, seed,
        ", ".join(s.text or s.action for s in segments), cfg.method)


# -- a motion to start from -------------------------------------------------------------------------

def _check_start(motion: np.ndarray, joints: int, loaded: LoadedODMO) -> np.ndarray:
    motion = np.asarray(motion, dtype=np.float32)
    if motion.ndim != 3 or motion.shape[1:] != (joints, 3):
        raise UserError(f"the motion to start from must be (frames, {joints}, 3) for the model's skeleton "
                        f"{loaded.dataset['skeleton']}, got shape {motion.shape}")
    if len(motion) < 2:
        raise UserError(f"the motion to start from has {len(motion)} frame(s); it needs at least 2")
    if not np.isfinite(motion).all():
        raise UserError("the motion to start from holds NaN or infinite values")
    return motion


def read_start(path: str | Path, loaded: LoadedODMO) -> np.ndarray:
    """The motion `--start-from` names, in the model's skeleton, frame and fps -> (L0, J, 3) float32:
    a samples file (.npz: its first motion), a (frames, joints, 3) .npy in the dataset's units, or a
    BVH file (read through the built-in joint maps of `odmo data prepare --format bvh`)."""
    from odmo_cli.data.bvh_import import BUILTIN_MAPS, resample, to_target
    from odmo_cli.data.manifest import load_manifest
    from odmo_cli.formats.bvh import read_bvh
    from odmo_cli.formats.samples import read_samples
    from odmo_cli.generation.generate import read_prefix

    path = Path(path)
    if not path.is_file():
        raise UserError(f"--start-from: file not found: {path}")
    fps, skeleton = float(loaded.dataset["fps"]), loaded.dataset["skeleton"]
    suffix = path.suffix.lower()
    if suffix == ".npz":
        f = read_samples(path, rows=slice(0, 1))
        if f["skeleton"] != skeleton:
            raise UserError(f"--start-from {path.name} has skeleton {f['skeleton']}; the model's is {skeleton}")
        if f["n"] == 0:
            raise UserError(f"--start-from {path.name} holds no motion")
        motion = f["motions"][0]
        if abs(f["fps"] - fps) > 1e-6:
            motion = resample(motion, f["fps"], fps)
    elif suffix == ".npy":
        motion = read_prefix(path)
    elif suffix == ".bvh":
        clip = read_bvh(path)
        jmap = next((m for m in BUILTIN_MAPS if m.skeleton == skeleton and m.applies_to(clip.names)), None)
        if jmap is None:
            raise UserError(f"--start-from {path.name}: no built-in joint map from its hierarchy (root "
                            f"{clip.names[0]}) to {skeleton}")
        motion, _ = to_target(clip, jmap, get_skeleton(skeleton), load_manifest(loaded.dataset["name"]), fps)
    else:
        raise UserError(f"--start-from must be a samples .npz, a (frames, joints, 3) .npy or a .bvh file, got {path.name}")
    return _check_start(motion, loaded.model.cfg.n_joints, loaded)
