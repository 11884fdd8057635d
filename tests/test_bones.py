"""A generated body keeps its size: ODMO's decode gives every bone one length and the torso one shape
(ODMOConfig.bones "rigid"), and such motions export to BVH, whose bones are rigid, exactly."""

from __future__ import annotations

import numpy as np
import torch

from odmo_cli.checkpoint import load_model
from odmo_cli.formats.bvh import export_motions
from odmo_cli.generation.generate import sample
from odmo_cli.geometry.skeletons import get_skeleton
from odmo_cli.measures.plausibility import bone_variation
from odmo_cli.models.odmo import ODMO, ODMOConfig


def decoded(bones: str, skeleton: str = "cmu20") -> np.ndarray:
    torch.manual_seed(0)  # an untrained model: its bones stretch from frame to frame
    model = ODMO(ODMOConfig(n_joints=20, n_classes=2, length=12, skeleton=skeleton, bones=bones)).eval()
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        _, motion = model.decode(torch.randn(6, 20, generator=g), torch.tensor([0, 1] * 3), torch.randn(6, 3, generator=g))
    return motion.numpy()


def test_rigid_decode_keeps_every_bone_at_one_length():
    parents = get_skeleton("cmu20").parents
    assert bone_variation(decoded("free"), parents).min() > 1e-3  # the pose decoder's own joints stretch
    assert bone_variation(decoded("rigid"), parents).max() < 1e-5
    # without a skeleton there is nothing to project on: the joints as drawn
    assert np.array_equal(decoded("rigid", skeleton=""), decoded("free"))


def test_a_shipped_model_samples_rigid_bodies_that_export_exactly(tmp_path):
    loaded = load_model("humanact12")
    assert loaded.model.cfg.skeleton == "humanact12" and loaded.model.cfg.bones == "rigid"
    batch = sample(loaded, ["jump", "run"], 3, seed=0)
    sk = get_skeleton("humanact12")
    assert bone_variation(batch.motions, sk.parents).max() < 1e-4  # float32 rounding of metres
    report = export_motions(batch.motions, batch.actions, sk, 20.0, tmp_path / "bvh")
    assert report.max_error_mm < 0.1 and report.max_stretch_mm < 0.1


def test_l_bone_is_zero_for_the_clips_body_and_the_squared_stretch_otherwise():
    from odmo_cli.models.losses import bone_length_error

    sk = get_skeleton("cmu20")
    g = torch.Generator().manual_seed(0)
    rest = torch.randn(20, 3, generator=g)
    real = rest.expand(2, 8, 20, 3).clone()  # a rigid body, still
    assert torch.allclose(bone_length_error(real + 0.3, real, sk.parents, sk.legs[0][:3]), torch.zeros(2), atol=1e-6)
    grown = real.clone()
    grown[:, :, 13:16] += (real[:, :, 13] - real[:, :, 12])[:, :, None] * 0.5  # the left thigh half as long again
    child = [j for j, p in enumerate(sk.parents) if p >= 0]
    thigh = float((rest[13] - rest[12]).norm())
    leg = thigh + float((rest[14] - rest[13]).norm())
    expected = (0.5 * thigh / leg) ** 2 / len(child)  # one bone of 19 off by half its length, at every frame
    assert torch.allclose(bone_length_error(grown, real, sk.parents, sk.legs[0][:3]), torch.full((2,), expected), rtol=1e-4)
