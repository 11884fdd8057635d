"""`odmo_cli.data`: clip rules (crop/pad/shift), readers (real releases and fixtures), dataset
summaries with checksum verification, samplers, splits, the motion-folder writer and the demo
subsets.

Real-data tests read $ODMO_DATA_DIR (see tests/conftest.py) and are skipped when it is unset.
"""

from __future__ import annotations

import csv
import dataclasses
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from odmo_cli.data.dataset import (
    MotionDataset,
    crop_pad_shift,
    mirror,
    mirror_map,
    pair_indices,
    random_start,
    split_indices,
    stratified_indices,
)
from odmo_cli.data.demo import demo_folder, load_demo, pick_demo
from odmo_cli.data.locate import manifest_for_folder, resolve
from odmo_cli.data.manifest import listing_digest, load_manifest, sha256_file
from odmo_cli.data.prepare import prepare, summarize, write_folder
from odmo_cli.data.readers import ClipSet, read_clip, read_dataset
from odmo_cli.errors import UserError

HUMANACT12_COUNTS = [215, 47, 50, 94, 88, 218, 54, 77, 56, 61, 140, 91]
CMU_COUNTS = {"walk": 474, "run": 109, "jump": 108, "animal_behavior": 101, "dance": 77, "step": 68,
              "climb": 33}


@pytest.fixture(scope="module")
def ha12_manifest():
    return load_manifest("humanact12")


@pytest.fixture(scope="module")
def cmu_manifest():
    return load_manifest("cmu_mocap")


@pytest.fixture(scope="module")
def real_ha12(humanact12_dir, ha12_manifest) -> ClipSet:
    return read_dataset(humanact12_dir, ha12_manifest)


@pytest.fixture(scope="module")
def real_cmu(cmu_dir, cmu_manifest) -> ClipSet:
    return read_dataset(cmu_dir, cmu_manifest)


def _ramp(n_frames: int, n_joints: int = 3) -> np.ndarray:
    """(n_frames, J, 3) whose value encodes (frame, joint, axis): easy to follow through crops."""
    t = np.arange(n_frames, dtype=np.float64)[:, None, None]
    j = np.arange(n_joints, dtype=np.float64)[None, :, None]
    a = np.arange(3, dtype=np.float64)[None, None, :]
    return 100.0 * t + 10.0 * j + a + 5.0


# ================================================================ crop / pad / shift


def test_crop_pad_shift_crops_at_start():
    m = _ramp(10)
    out = crop_pad_shift(m, 4, start=3)
    assert out.shape == (4, 3, 3) and out.dtype == np.float32
    np.testing.assert_allclose(out, m[3:7] - m[3, 0])
    np.testing.assert_array_equal(out[0, 0], 0.0)  # first root at the origin


def test_crop_pad_shift_pads_with_last_frame():
    m = _ramp(3)
    out = crop_pad_shift(m, 7)
    assert out.shape == (7, 3, 3)
    np.testing.assert_allclose(out[:3], m - m[0, 0])
    for t in range(3, 7):
        np.testing.assert_allclose(out[t], m[2] - m[0, 0])  # the LAST frame, not zeros or the first


def test_crop_pad_shift_exact_length_and_single_frame():
    m = _ramp(6)
    np.testing.assert_allclose(crop_pad_shift(m, 6), m - m[0, 0])
    one = crop_pad_shift(_ramp(1), 5)
    assert one.shape == (5, 3, 3)
    np.testing.assert_allclose(one, np.broadcast_to(_ramp(1)[0] - _ramp(1)[0, 0], (5, 3, 3)))


def test_crop_pad_shift_first_root_at_origin_keeps_lmp():
    rng = np.random.default_rng(0)
    m = rng.normal(size=(30, 24, 3)) + 7.0
    out = crop_pad_shift(m, 20, start=5)
    np.testing.assert_allclose(out[0, 0], 0.0, atol=1e-6)
    # a rigid shift only: joint offsets from the root are unchanged
    np.testing.assert_allclose(out - out[:, :1], m[5:25] - m[5:25, :1], atol=1e-5)


@pytest.mark.parametrize("n_frames,length,start", [(10, 4, 7), (10, 4, -1), (3, 7, 1), (10, 10, 1)])
def test_crop_pad_shift_bad_start(n_frames, length, start):
    with pytest.raises(ValueError, match="out of range"):
        crop_pad_shift(_ramp(n_frames), length, start)


def test_crop_pad_shift_last_valid_start():
    out = crop_pad_shift(_ramp(10), 4, start=6)
    np.testing.assert_allclose(out[-1], _ramp(10)[9] - _ramp(10)[6, 0])


def test_random_start_bounds():
    rng = np.random.default_rng(0)
    starts = [random_start(10, 4, rng) for _ in range(400)]
    assert min(starts) == 0 and max(starts) == 6  # every valid start 0..T_i - T is reachable
    assert set(starts) == set(range(7))
    assert all(random_start(n, 60, rng) == 0 for n in (1, 30, 59, 60))  # short clips start at 0
    assert random_start(61, 60, rng) in (0, 1)


def test_random_start_is_seeded():
    a = [random_start(100, 60, np.random.default_rng(3)) for _ in range(3)]
    assert len(set(a)) == 1
    b = np.random.default_rng(5)
    c = np.random.default_rng(5)
    assert [random_start(100, 60, b) for _ in range(10)] == [random_start(100, 60, c) for _ in range(10)]


def test_motion_dataset_items(humanact12_fixture, ha12_manifest):
    clips = read_dataset(humanact12_fixture, ha12_manifest)
    ds = MotionDataset(clips, rng=np.random.default_rng(1))
    assert len(ds) == 24 and ds.length == 60
    motion, label = ds[5]
    assert isinstance(motion, torch.Tensor) and motion.dtype == torch.float32
    assert tuple(motion.shape) == (60, 24, 3) and label == int(clips.labels[5])
    assert torch.count_nonzero(motion[0, 0]) == 0
    x, y = ds.batch([0, 3, 23])
    assert tuple(x.shape) == (3, 60, 24, 3) and y.tolist() == clips.labels[[0, 3, 23]].tolist()
    # same seed, same crops; without random crops every item starts at frame 0
    a = MotionDataset(clips, rng=np.random.default_rng(2)).batch(range(6))[0]
    b = MotionDataset(clips, rng=np.random.default_rng(2)).batch(range(6))[0]
    c = MotionDataset(clips, rng=np.random.default_rng(3)).batch(range(6))[0]
    assert torch.equal(a, b) and not torch.equal(a, c)
    fixed = MotionDataset(clips, random_crop=False)
    np.testing.assert_allclose(fixed[2][0].numpy(), crop_pad_shift(clips.motions[2], 60, 0))


# ================================================================ readers: real data


def test_humanact12_real(real_ha12, ha12_manifest):
    clips = real_ha12
    assert len(clips) == 1191
    assert clips.counts().tolist() == HUMANACT12_COUNTS
    assert clips.counts().tolist() == [a.count for a in ha12_manifest.actions]
    assert not clips.problems
    assert len(set(clips.modes.tolist())) == 34  # Action2Motion's fine labels
    assert all(m // 100 == lab + 1 for m, lab in zip(clips.modes, clips.labels))
    assert all(m.dtype == np.float32 and m.ndim == 3 and m.shape[1:] == (24, 3) for m in clips.motions)
    lengths = [len(m) for m in clips.motions]
    assert min(lengths) == 8 and max(lengths) == 470 and np.median(lengths) == 60
    # metres, up = -y: head (15) minus pelvis (0) is about (0, -0.56, -0.11)
    head = np.mean([(m[:, 15] - m[:, 0]).mean(0) for m in clips.motions], axis=0)
    assert -0.65 < head[1] < -0.45
    assert abs(head[0]) < 0.05 and abs(head[1]) > 3 * abs(head[2])
    assert set(clips.subjects) >= {"P01", "P12"} and all(s.startswith("P") for s in clips.subjects)


def test_humanact12_real_values_match_files(real_ha12, humanact12_dir):
    i = real_ha12.names.index("P01G01R01F0001T0064A0101")
    raw = np.load(humanact12_dir / "P01G01R01F0001T0064A0101.npy")
    assert raw.dtype == np.float64 and raw.shape == (64, 24, 3)
    np.testing.assert_allclose(real_ha12.motions[i], raw.astype(np.float32))
    assert real_ha12.labels[i] == 0 and real_ha12.modes[i] == 101


def test_cmu_real(real_cmu, cmu_dir, cmu_manifest):
    clips = real_cmu
    assert len(clips) == 970
    assert dict(zip(cmu_manifest.action_names, clips.counts().tolist())) == CMU_COUNTS
    assert len(cmu_manifest.actions) == 7 and "wash" not in cmu_manifest.action_names
    with open(cmu_dir / "pose_clip.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 1088
    wash = {r["motion"] for r in rows if r["action_type"] == "Wash"}
    assert len(wash) == 118 and not wash & set(clips.names)
    assert all(m.dtype == np.float32 and m.shape[1:] == (20, 3) for m in clips.motions)
    assert (clips.modes == -1).all()
    # scale 1/20 applied
    name = clips.names[0]
    raw = np.load(cmu_dir / "mocap_3djoints" / f"{name}.npy")
    np.testing.assert_allclose(clips.motions[0], raw / 20.0, rtol=1e-6, atol=1e-6)
    # ~metres, up = +y: head (3) above the root by roughly half a metre
    head = np.mean([(m[:, 3] - m[:, 0]).mean(0) for m in clips.motions], axis=0)
    assert 0.35 < head[1] < 0.7


# ================================================================ readers: fixtures


def test_humanact12_fixture_reader(humanact12_fixture, ha12_manifest):
    clips = read_dataset(humanact12_fixture, ha12_manifest)
    assert len(clips) == 24 and clips.counts().tolist() == [2] * 12
    assert sorted(set(clips.modes.tolist())) == sorted(a * 100 + f for a in range(1, 13) for f in (1, 2))
    assert set(clips.subjects) == {"P01", "P02"}
    name = clips.names[7]
    raw = np.load(humanact12_fixture / f"{name}.npy")
    assert raw.dtype == np.float64
    assert clips.motions[7].dtype == np.float32 and clips.motions[7].shape == (70, 24, 3)
    np.testing.assert_allclose(clips.motions[7], raw.astype(np.float32))
    assert clips.labels[7] == int(name[-4:-2]) - 1


def test_cmu_fixture_reader_ignores_wash(cmu_fixture, cmu_manifest):
    clips = read_dataset(cmu_fixture, cmu_manifest)
    assert len(clips) == 14 and clips.counts().tolist() == [2] * 7
    assert not any(n.startswith("08_") for n in clips.names)  # Wash rows are class 8 in the fixture
    assert (cmu_fixture / "mocap_3djoints" / "08_01.npy").is_file()
    i = clips.names.index("03_02")
    assert cmu_manifest.actions[clips.labels[i]].name == "jump"
    np.testing.assert_allclose(clips.motions[i], np.load(cmu_fixture / "mocap_3djoints" / "03_02.npy") * 0.05,
                               rtol=1e-6)
    assert clips.subjects[i] == "03"


def test_cmu_fixture_listed_but_missing(cmu_fixture, cmu_manifest):
    (cmu_fixture / "mocap_3djoints" / "02_01.npy").unlink()
    with pytest.raises(UserError, match="02_01.npy: listed in pose_clip.csv but missing"):
        read_dataset(cmu_fixture, cmu_manifest)
    loose = read_dataset(cmu_fixture, cmu_manifest, strict=False)
    assert len(loose) == 13 and any("02_01" in p for p in loose.problems)


def test_motion_folder_reader(tmp_path, make_motion_folder):
    folder = make_motion_folder(tmp_path / "mf", splits=["train", "val", "test"] * 8)
    manifest = manifest_for_folder(folder)
    assert manifest.format == "folder" and manifest.name == "humanact12" and manifest.scale == 1.0
    clips = read_dataset(folder, manifest)
    assert len(clips) == 24 and clips.counts().tolist() == [2] * 12
    assert clips.modes.tolist() == [i % 2 for i in range(24)]
    assert clips.splits[:3] == ["train", "val", "test"] and clips.subjects[:2] == ["S0", "S1"]
    np.testing.assert_array_equal(clips.motions[4], np.load(folder / "clip004.npy"))


def test_motion_folder_action_names_are_forgiving(tmp_path, make_motion_folder):
    actions = ["Warm up", "WALK", "run", "jump", "drink", "lift-dumbbell", "sit", "eat",
               "turn steering wheel", "phone", "boxing", "throw"]
    folder = make_motion_folder(tmp_path / "mf", actions=actions)
    clips = read_dataset(folder, manifest_for_folder(folder))
    assert clips.labels.tolist() == list(range(12))


def test_motion_folder_unknown_action_is_an_error_even_when_lenient(tmp_path, make_motion_folder):
    folder = make_motion_folder(tmp_path / "mf", actions=["walk", "run", "moonwalk"])
    manifest = manifest_for_folder(folder)
    for strict in (True, False):
        with pytest.raises(UserError, match=r"'moonwalk' of clip002 is not in the manifest; valid: warm_up"):
            read_dataset(folder, manifest, strict=strict)


@pytest.mark.parametrize("kind,message", [
    ("garbage", "unreadable npy"), ("truncated", "unreadable npy"), ("nan", "non-finite"),
    ("inf", "non-finite"), ("joints", "22 joints, skeleton humanact12 has 24"),
    ("shape", r"expected \(T, 24, 3\)"), ("empty", r"expected \(T, 24, 3\)"), ("strings", "non-numeric"),
])
def test_bad_clip_strict_and_lenient(humanact12_fixture, ha12_manifest, spoil_clip, kind, message):
    bad = sorted(humanact12_fixture.glob("*.npy"))[4]
    spoil_clip(bad, kind)
    with pytest.raises(UserError, match=message) as info:
        read_dataset(humanact12_fixture, ha12_manifest)
    assert bad.name in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(UserError, match=message):
        read_clip(bad, ha12_manifest)
    loose = read_dataset(humanact12_fixture, ha12_manifest, strict=False)
    assert len(loose) == 23 and bad.stem not in loose.names
    assert len(loose.problems) == 1 and bad.name in loose.problems[0]


def test_humanact12_bad_names_and_codes(humanact12_fixture, ha12_manifest):
    src = sorted(humanact12_fixture.glob("*.npy"))[0]
    shutil.copy(src, humanact12_fixture / "P01G01R01F0001T0064A1301.npy")  # action code 13
    shutil.copy(src, humanact12_fixture / "walk_01.npy")  # not a release name
    with pytest.raises(UserError, match="2 problem"):
        read_dataset(humanact12_fixture, ha12_manifest)
    loose = read_dataset(humanact12_fixture, ha12_manifest, strict=False)
    assert len(loose) == 24
    assert any("A1301" in p and "not in the manifest" in p for p in loose.problems)
    assert any("walk_01.npy" in p for p in loose.problems)


def test_empty_class(tmp_path, make_humanact12, ha12_manifest):
    folder = make_humanact12(tmp_path / "ha12", actions=range(1, 12))  # no 'throw'
    with pytest.raises(UserError, match="empty classes .*: throw$"):
        read_dataset(folder, ha12_manifest)
    loose = read_dataset(folder, ha12_manifest, strict=False)
    assert len(loose) == 22 and loose.counts()[11] == 0
    assert any("empty classes" in p and "throw" in p for p in loose.problems)


def test_missing_and_empty_folders(tmp_path, ha12_manifest, cmu_manifest):
    with pytest.raises(UserError, match="dataset folder not found"):
        read_dataset(tmp_path / "nope", ha12_manifest)
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="no HumanAct12 .npy files"):
        read_dataset(tmp_path / "empty", ha12_manifest)
    with pytest.raises(UserError, match="no pose_clip.csv"):
        read_dataset(tmp_path / "empty", cmu_manifest)


def test_resolve_by_name_and_folder(tmp_path, humanact12_fixture, cmu_fixture, make_motion_folder):
    root = tmp_path / "root"
    make_motion_folder(tmp_path / "mf")
    shutil.copytree(humanact12_fixture, root / "humanact12" / "HumanAct12")
    manifest, folder = resolve("humanact12", root)
    assert manifest.name == "humanact12" and folder == root / "humanact12" / "HumanAct12"
    assert resolve(str(cmu_fixture))[0].name == "cmu_mocap"
    assert resolve(str(humanact12_fixture))[0].name == "humanact12"
    assert resolve(str(tmp_path / "mf"))[0].format == "folder"
    with pytest.raises(UserError, match="dataset cmu_mocap not found under"):
        resolve("cmu_mocap", root)
    shutil.copytree(cmu_fixture, root / "cmu_mocap")
    assert resolve("cmu", root)[0].name == "cmu_mocap"  # the short name, as in `odmo ship cmu`
    with pytest.raises(UserError, match="unknown dataset 'nosuch'.*humanact12"):
        resolve("nosuch", root)
    with pytest.raises(UserError, match="holds a dataset below it"):
        resolve(str(root))


# ================================================================ summaries and checksums


def test_summarize_real_humanact12(humanact12_dir, ha12_manifest):
    s = summarize(ha12_manifest, humanact12_dir)
    assert s.digest_ok is True
    assert (s.missing, s.extra, s.corrupt, s.problems) == ([], [], [], [])
    assert s.total == 1191 and [r.clips for r in s.rows] == HUMANACT12_COUNTS
    assert all(r.clips == r.expected for r in s.rows)
    assert sum(r.modes for r in s.rows) == 34 and all(r.modes >= 1 for r in s.rows)
    assert min(r.min_len for r in s.rows) == 8 and max(r.max_len for r in s.rows) == 470


def test_summarize_real_cmu(cmu_dir, cmu_manifest):
    s = summarize(cmu_manifest, cmu_dir)
    assert s.digest_ok is True and (s.missing, s.extra, s.corrupt) == ([], [], [])
    assert s.total == 970 and {r.name: r.clips for r in s.rows} == CMU_COUNTS
    assert all(r.modes == 0 for r in s.rows)


@pytest.fixture
def checked_copy(tmp_path, humanact12_dir, ha12_manifest):
    """Three real HumanAct12 clips copied to tmp, with a manifest whose .sha256 lists them."""
    names = ["P01G01R01F0001T0064A0101.npy", "P01G01R01F0449T0505A0201.npy",
             "P01G01R01F0718T0825A0301.npy"]
    folder = tmp_path / "copy"
    folder.mkdir()
    for n in names:
        shutil.copy(humanact12_dir / n, folder / n)
    listing = dict(line.split()[::-1] for line in
                   ha12_manifest.path.with_suffix(".sha256").read_text().splitlines() if line.strip())
    checks = {n: listing[n] for n in names}
    assert checks == {n: sha256_file(folder / n) for n in names}  # the shipped listing is right
    (tmp_path / "three.sha256").write_text("".join(f"{checks[n]}  {n}\n" for n in names))
    manifest = dataclasses.replace(ha12_manifest, path=tmp_path / "three.toml",
                                   digest=listing_digest(checks), n_files=3)
    return manifest, folder


def test_summarize_checks_an_intact_copy(checked_copy):
    manifest, folder = checked_copy
    s = summarize(manifest, folder)
    assert s.digest_ok is True and (s.missing, s.extra, s.corrupt) == ([], [], [])
    assert s.total == 3 and [r.clips for r in s.rows][:3] == [1, 1, 1]
    assert any("empty classes" in p for p in s.problems)  # lenient: reported, not raised
    assert summarize(manifest, folder, verify=False).digest_ok is None


def test_summarize_flags_missing_extra_corrupt(checked_copy):
    manifest, folder = checked_copy
    (folder / "P01G01R01F0449T0505A0201.npy").unlink()  # missing
    shutil.copy(folder / "P01G01R01F0001T0064A0101.npy", folder / "P02G01R01F0001T0064A0401.npy")  # extra
    corrupt = folder / "P01G01R01F0718T0825A0301.npy"
    arr = np.load(corrupt)
    arr[0, 0, 0] += 0.001  # still a valid clip, different bytes
    np.save(corrupt, arr)
    (folder / ".DS_Store").write_bytes(b"x")  # hidden files are not "extra"
    s = summarize(manifest, folder)
    assert s.missing == ["P01G01R01F0449T0505A0201.npy"]
    assert s.extra == ["P02G01R01F0001T0064A0401.npy"]
    assert s.corrupt == ["P01G01R01F0718T0825A0301.npy"]
    assert s.digest_ok is False
    j = s.to_json()
    assert j["digest_ok"] is False and j["clips"] == 3 and j["missing"] == s.missing


def test_summarize_wrong_digest(checked_copy):
    manifest, folder = checked_copy
    s = summarize(dataclasses.replace(manifest, digest="0" * 64), folder)
    assert (s.missing, s.corrupt) == ([], []) and s.digest_ok is False


# ================================================================ samplers and splits


def test_stratified_indices_class_balanced():
    counts = [1, 5, 40, 400, 3000]
    labels = np.repeat(np.arange(5), counts)
    idx = stratified_indices(labels, 12_000, np.random.default_rng(0))
    assert idx.shape == (12_000,) and idx.dtype == np.int64
    assert idx.min() >= 0 and idx.max() < len(labels)
    observed = np.bincount(labels[idx], minlength=5)
    expected = 12_000 / 5
    chi2 = ((observed - expected) ** 2 / expected).sum()
    assert chi2 < 20.0, observed  # 4 dof: p < 0.001; drawing by clip would give ~11,000 of class 4
    # inside a class every clip is used (here the 5-clip class)
    assert set(idx[labels[idx] == 1].tolist()) == set(np.flatnonzero(labels == 1).tolist())
    assert (idx[labels[idx] == 0] == 0).all()


def test_stratified_indices_seeded():
    labels = np.repeat(np.arange(3), [2, 10, 50])
    a = stratified_indices(labels, 100, np.random.default_rng(7))
    b = stratified_indices(labels, 100, np.random.default_rng(7))
    c = stratified_indices(labels, 100, np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.fixture(scope="module")
def skewed_labels():
    return np.repeat(np.arange(4), [3, 10, 100, 900])


def test_pair_indices_half_same(skewed_labels):
    pairs = pair_indices(skewed_labels, 4000, np.random.default_rng(0), same_fraction=0.5)
    assert pairs.shape == (4000, 2)
    same = skewed_labels[pairs[:, 0]] == skewed_labels[pairs[:, 1]]
    assert 0.46 < same.mean() < 0.54
    for side in (0, 1):  # both sides class-balanced
        share = np.bincount(skewed_labels[pairs[:, side]], minlength=4) / 4000
        assert np.all(np.abs(share - 0.25) < 0.03), share


def test_pair_indices_none_and_all_same(skewed_labels):
    rng = np.random.default_rng(1)
    never = pair_indices(skewed_labels, 2000, rng, same_fraction=0.0)
    assert not (skewed_labels[never[:, 0]] == skewed_labels[never[:, 1]]).any()
    always = pair_indices(skewed_labels, 2000, rng, same_fraction=1.0)
    assert (skewed_labels[always[:, 0]] == skewed_labels[always[:, 1]]).all()
    free = pair_indices(skewed_labels, 4000, rng)  # independent sides: same class with p = 1/C
    assert 0.21 < (skewed_labels[free[:, 0]] == skewed_labels[free[:, 1]]).mean() < 0.29


def test_pair_indices_single_class():
    labels = np.zeros(10, dtype=np.int64)
    with pytest.raises(UserError, match="at least two actions"):
        pair_indices(labels, 10, np.random.default_rng(0), same_fraction=0.5)
    pairs = pair_indices(labels, 10, np.random.default_rng(0), same_fraction=1.0)
    assert pairs.shape == (10, 2)


def _clips_with_labels(labels, splits=None) -> ClipSet:
    manifest = load_manifest("humanact12")
    n = len(labels)
    return ClipSet(manifest, Path("."), [np.zeros((1, 24, 3), np.float32)] * n, np.asarray(labels, np.int64),
                   [f"c{i}" for i in range(n)], np.full(n, -1, np.int64), splits=list(splits or []))


def test_split_indices_deterministic_per_class_disjoint():
    labels = np.repeat(np.arange(4), [1, 10, 21, 50])
    clips = _clips_with_labels(labels)
    train, val = split_indices(clips, 0.2, seed=3)
    train2, val2 = split_indices(clips, 0.2, seed=3)
    np.testing.assert_array_equal(train, train2)
    np.testing.assert_array_equal(val, val2)
    assert not set(train) & set(val)
    assert sorted(np.concatenate([train, val]).tolist()) == list(range(len(labels)))
    assert np.bincount(labels[val], minlength=4).tolist() == [0, 2, 4, 10]  # round(n_c * 0.2) per class
    other = [split_indices(clips, 0.2, seed=s)[1] for s in (4, 5)]
    assert any(not np.array_equal(val, o) for o in other)
    t0, v0 = split_indices(clips, 0.0, seed=3)
    assert len(v0) == 0 and len(t0) == len(labels)


@pytest.mark.parametrize("fraction", [-0.1, 1.0, 1.5])
def test_split_indices_bad_fraction(fraction):
    with pytest.raises(UserError, match="validation fraction"):
        split_indices(_clips_with_labels([0, 0, 1, 1]), fraction, seed=0)


def test_split_indices_honours_split_column(tmp_path, make_motion_folder):
    splits = ["train", "val", "train", "test"] * 6
    folder = make_motion_folder(tmp_path / "mf", splits=splits)
    clips = read_dataset(folder, manifest_for_folder(folder))
    train, val = split_indices(clips, 0.5, seed=0)
    assert train.tolist() == [i for i, s in enumerate(splits) if s == "train"]
    assert val.tolist() == [i for i, s in enumerate(splits) if s in ("val", "test")]
    assert split_indices(clips, 0.5, seed=9)[1].tolist() == val.tolist()  # the seed plays no part


# ================================================================ writing motion folders, demo


def test_prepare_round_trip(tmp_path, humanact12_fixture, ha12_manifest):
    out = tmp_path / "prepared"
    clips = prepare(ha12_manifest, humanact12_fixture, out)
    assert {p.name for p in out.iterdir()} == {f"{n}.npy" for n in clips.names} | {"dataset.toml", "index.csv"}
    assert len(clips.names) == 24
    back = read_dataset(out, manifest_for_folder(out))
    assert back.manifest.format == "folder" and back.manifest.scale == 1.0
    assert back.manifest.action_names == ha12_manifest.action_names
    assert back.names == clips.names and back.labels.tolist() == clips.labels.tolist()
    assert back.modes.tolist() == clips.modes.tolist() and back.subjects == clips.subjects
    for a, b in zip(back.motions, clips.motions):
        np.testing.assert_array_equal(a, b)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp folder left


def test_prepare_applies_scale(tmp_path, cmu_fixture, cmu_manifest):
    out = tmp_path / "prepared"
    prepare(cmu_manifest, cmu_fixture, out)
    back = read_dataset(out, manifest_for_folder(out))
    i = back.names.index("05_01")
    np.testing.assert_allclose(back.motions[i], np.load(cmu_fixture / "mocap_3djoints" / "05_01.npy") / 20,
                               rtol=1e-6)
    assert back.manifest.skeleton_name == "cmu20" and back.manifest.up_axis == "+y"
    assert len(back) == 14  # Wash left out


def test_prepared_folder_has_usual_permissions(tmp_path, humanact12_fixture, ha12_manifest):
    out = tmp_path / "prepared"
    prepare(ha12_manifest, humanact12_fixture, out)
    mask = os.umask(0)
    os.umask(mask)
    assert out.stat().st_mode & 0o777 == 0o777 & ~mask


def test_write_folder_refuses_existing_and_leaves_nothing_on_failure(tmp_path, humanact12_fixture,
                                                                     ha12_manifest):
    clips = read_dataset(humanact12_fixture, ha12_manifest)
    (tmp_path / "exists").mkdir()
    with pytest.raises(UserError, match="already exists"):
        write_folder(clips, tmp_path / "exists")
    assert list((tmp_path / "exists").iterdir()) == []
    with pytest.raises(UserError, match="does not exist"):
        write_folder(clips, tmp_path / "no" / "such" / "out")
    clips.motions[10] = None  # fails half-way through writing
    with pytest.raises(AttributeError):
        write_folder(clips, tmp_path / "half")
    assert not (tmp_path / "half").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exists", "ha12"]


def test_prepare_bad_source_writes_nothing(tmp_path, humanact12_fixture, ha12_manifest):
    np.save(sorted(humanact12_fixture.glob("*.npy"))[-1], np.full((5, 24, 3), np.nan))
    with pytest.raises(UserError, match="non-finite"):
        prepare(ha12_manifest, humanact12_fixture, tmp_path / "out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ha12"]


def test_demo_subsets_load():
    ha = load_demo("humanact12")
    assert ha.names == read_dataset(demo_folder("humanact12"), manifest_for_folder(demo_folder("humanact12"))).names
    assert len(ha) == 36 and ha.counts().tolist() == [3] * 12
    assert ha.manifest.skeleton_name == "humanact12" and ha.manifest.clip_length == 60
    assert all(m.dtype == np.float32 and m.shape[1:] == (24, 3) and len(m) <= 120 for m in ha.motions)
    cmu = load_demo("cmu")
    assert len(cmu) == 21 and cmu.counts().tolist() == [3] * 7
    assert cmu.manifest.skeleton_name == "cmu20"
    assert all(m.shape[1:] == (20, 3) and len(m) <= 200 for m in cmu.motions)
    with pytest.raises(UserError, match="no demo subset for 'uestc'"):
        demo_folder("uestc")


def test_demo_matches_real_release(real_ha12):
    demo = read_dataset(demo_folder("humanact12"), manifest_for_folder(demo_folder("humanact12")))
    for name, motion in zip(demo.names, demo.motions):
        full = real_ha12.motions[real_ha12.names.index(name)]
        np.testing.assert_array_equal(motion, full[:120])
    assert demo.names == [real_ha12.names[i] for i in pick_demo(real_ha12)]


def test_pick_demo_prefers_distinct_modes(humanact12_fixture, ha12_manifest):
    clips = read_dataset(humanact12_fixture, ha12_manifest)
    picks = pick_demo(clips, per_action=2)
    assert len(picks) == 24
    for k in range(12):
        mine = [i for i in picks if clips.labels[i] == k]
        assert len(mine) == 2 and len({int(clips.modes[i]) for i in mine}) == 2
    assert len(pick_demo(clips, per_action=5)) == 24  # no more than each action has


def test_prepare_folder_keeps_split_column(tmp_path, make_motion_folder):
    splits = ["train", "test", "val"] * 8
    src = make_motion_folder(tmp_path / "mf", splits=splits)
    out = tmp_path / "again"
    prepare(manifest_for_folder(src), src, out)
    back = read_dataset(out, manifest_for_folder(out))
    assert back.splits == splits
    assert split_indices(back, 0.5, seed=0)[0].tolist() == [i for i, s in enumerate(splits) if s == "train"]
    # without a split column none is written
    out2 = tmp_path / "plain"
    src2 = make_motion_folder(tmp_path / "mf2")
    prepare(manifest_for_folder(src2), src2, out2)
    with open(out2 / "index.csv", newline="") as f:
        assert next(csv.reader(f)) == ["motion", "action", "mode", "subject"]


def test_mirror_swaps_partner_joints_keeps_the_facing_and_undoes_itself():
    """HumanAct12's clips face along z with the hips side by side along x: mirroring across x swaps
    the sides and keeps the figure facing forwards (left hip at +x before and after)."""
    skeleton = load_manifest("humanact12").skeleton
    perm, axis = mirror_map(skeleton.joint_names), skeleton.ground_axes[0]
    left, right = skeleton.joint_names.index("left_hip"), skeleton.joint_names.index("right_hip")
    motions = np.random.default_rng(0).normal(size=(3, 5, 24, 3)).astype(np.float32)  # (N, T, J, 3)
    motions[:, :, left, 0], motions[:, :, right, 0] = 0.1, -0.1
    out = mirror(motions, perm, axis)
    np.testing.assert_array_equal(out[:, :, left, 0], np.float32(0.1))
    np.testing.assert_array_equal(out[:, :, right, 0], np.float32(-0.1))
    np.testing.assert_array_equal(out[:, :, left, 1:], motions[:, :, right, 1:])
    np.testing.assert_array_equal(mirror(out, perm, axis), motions)
    as_tensor = mirror(torch.from_numpy(motions), perm, axis)
    assert isinstance(as_tensor, torch.Tensor) and as_tensor.dtype == torch.float32
    np.testing.assert_array_equal(as_tensor.numpy(), out)
