"""``Predictor.cameras_from_source`` and ``predict``'s argument checks, without a run: a Predictor of a scene whose
normalisation is a known similarity (the end-to-end tests with a trained run are in tests/e2e/test_evaluate.py)."""

import json
import math

import numpy as np
import pytest
import torch

from uncertsplat.config import EvalConfig
from uncertsplat.errors import UserError
from uncertsplat.predict import Predictor
from uncertsplat.types import Cameras

K = torch.tensor([[100.0, 0.0, 64.0], [0.0, 90.0, 48.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def bare_predictor(scale: float = 0.5, shift=(1.0, -2.0, 3.0)) -> Predictor:
    """A Predictor with nothing loaded but the scene's normalisation x_world = scale x_source + shift (all that
    cameras_from_source reads) and a config (predict's defaults)."""
    pred = Predictor.__new__(Predictor)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] *= scale
    T[:3, 3] = torch.tensor(shift, dtype=torch.float64)
    pred._world_from_source = T
    pred._cfg = pred.config = EvalConfig(num_samples=3, seed=4)
    pred.device = torch.device("cpu")
    pred.loaded = pred.scene = None  # (no model: cameras_from_source's note on poses that see none of it is skipped)
    return pred


def rotation(angle: float, axis: int) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    i, j = [a for a in range(3) if a != axis]
    R = torch.eye(3, dtype=torch.float64)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def a_pose() -> torch.Tensor:
    """[4,4] an OpenCV cam_from_world with a rotation about every axis and a translation."""
    M = torch.eye(4, dtype=torch.float64)
    M[:3, :3] = rotation(0.3, 0) @ rotation(-1.1, 1) @ rotation(2.0, 2)
    M[:3, 3] = torch.tensor([0.4, -1.5, 7.0], dtype=torch.float64)
    return M


def test_the_four_pose_conventions_of_one_pose_give_the_same_camera():
    pred = bare_predictor()
    cv = a_pose()  # cam_from_world, OpenCV axes
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))  # OpenCV <-> OpenGL camera axes
    gl = flip @ cv  # cam_from_world, OpenGL axes
    expected = pred.cameras_from_source(cv, K, 128, 96)
    for pose, transform, axes in ((torch.linalg.inv(cv), "world_from_cam", "opencv"), (gl, "cam_from_world", "opengl"),
                                  (torch.linalg.inv(gl), "world_from_cam", "opengl"),
                                  (torch.linalg.inv(gl), "world_from_cam", "blender")):
        got = pred.cameras_from_source(pose, K, 128, 96, transform=transform, axes=axes)
        torch.testing.assert_close(got.cam_from_world, expected.cam_from_world, atol=1e-6, rtol=0)
    # a Blender camera looking down its -z: its OpenCV z is the world direction it looks along
    blender = torch.eye(4, dtype=torch.float64)  # world_from_cam, at the origin, looking along the world's -z
    cam = bare_predictor(1.0, (0.0, 0.0, 0.0)).cameras_from_source(blender, K, 128, 96, transform="world_from_cam",
                                                                   axes="blender")
    world_from_cam = torch.linalg.inv(cam.cam_from_world[0].double())
    torch.testing.assert_close(world_from_cam[:3, 2], torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))
    with pytest.raises(UserError, match="unknown transform 'cam_to_world'"):
        pred.cameras_from_source(cv, K, 128, 96, transform="cam_to_world")
    with pytest.raises(UserError, match="unknown axes 'ros'"):
        pred.cameras_from_source(cv, K, 128, 96, axes="ros")


def test_a_pose_given_camera_to_world_gets_the_seed_of_its_world_to_camera_matrix():
    """A robot's camera-to-world pose is often the float64 inverse of a world-to-camera one whose rotation is
    orthonormal to float32's precision only; inverted back as [R^T, -R^T t] it came 1e-8 off the matrix it was made
    from, so ``pose_index`` seeded it apart and its maps differed (20 poses of 20). Now the same seed, for rotations
    about every axis and about one (entries exactly 0 one way, 1e-17 or -0.0 the other)."""
    from uncertsplat.eval.engine import pose_index

    pred = bare_predictor()
    gen = np.random.default_rng(0)
    poses = []
    for i in range(20):
        M = np.eye(4)
        angles = gen.uniform(-3, 3, 3)
        R = (rotation(angles[0], 0) @ rotation(angles[1], 1) @ rotation(angles[2], 2)) if i % 2 else rotation(
            angles[0], i % 3)
        M[:3, :3] = R.float().double().numpy()  # orthonormal to float32's precision, as a map's poses are
        M[:3, 3] = gen.normal(0, 5, 3)
        poses.append(M)
    for M in poses:
        a = pred.cameras_from_source(M, K, 128, 96)
        b = pred.cameras_from_source(np.linalg.inv(M), K, 128, 96, transform="world_from_cam")
        assert pose_index(a.cam_from_world[0], a.K[0]) == pose_index(b.cam_from_world[0], b.K[0])
    other = poses[0].copy()
    other[0, 3] += 1e-4
    a = pred.cameras_from_source(poses[0], K, 128, 96)
    c = pred.cameras_from_source(other, K, 128, 96)
    assert pose_index(a.cam_from_world[0], a.K[0]) != pose_index(c.cam_from_world[0], c.K[0])


def test_arrays_with_negative_strides_a_pose_that_needs_grad_and_one_name():
    """``np.flip`` or ``a[::-1]`` of poses (torch refused their negative strides), a tensor with ``requires_grad``
    (torch warned from inside), and ``names="cam"`` for one pose (split into its letters: "3 name(s)")."""
    import warnings

    pred = bare_predictor()
    M = a_pose().numpy()
    expected = pred.cameras_from_source(np.stack([M, np.linalg.inv(M)]), K, 128, 96)
    flipped = pred.cameras_from_source(np.stack([np.linalg.inv(M), M])[::-1], K.numpy()[None][::-1], 128, 96)
    torch.testing.assert_close(flipped.cam_from_world, expected.cam_from_world, atol=0, rtol=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pred.cameras_from_source(torch.from_numpy(M).requires_grad_(), K, 128, 96)
    assert pred.cameras_from_source(M, K, 128, 96, names="cam").image_names == ("cam",)
    with pytest.raises(UserError, match=r"1 name\(s\) for 2 pose\(s\)"):
        pred.cameras_from_source(np.stack([M, M]), K, 128, 96, names="cam")


def test_three_by_four_poses_get_the_last_row():
    """[N,3,4] is what pycolmap's Rigid3d.matrix() gives; one pose may come as [3,4] or [4,4], numpy or torch."""
    pred = bare_predictor()
    M = a_pose()
    full = pred.cameras_from_source(torch.stack([M, M.inverse()]), K, 128, 96)
    short = pred.cameras_from_source(np.stack([M[:3].numpy(), M.inverse()[:3].numpy()]), K.numpy(), 128, 96)
    torch.testing.assert_close(short.cam_from_world, full.cam_from_world, atol=0, rtol=0)
    one = pred.cameras_from_source(M[:3], K, 128.0, 96)  # a whole float is a whole number
    torch.testing.assert_close(one.cam_from_world, full.cam_from_world[:1], atol=0, rtol=0)
    assert (one.width, one.height) == (128, 96) and isinstance(one.width, int)


@pytest.mark.parametrize("change, match", [
    (lambda M: M.__setitem__((3, 2), 0.5), r"pose 1 has the last row \[0.0, 0.0, 0.5, 1.0\], not \[0, 0, 0, 1\]"),
    (lambda M: M.__setitem__((0, 3), float("nan")), "pose 1 has entries that are not finite"),
    (lambda M: M.__setitem__((2, 3), float("inf")), "pose 1 has entries that are not finite"),
    (lambda M: M.__setitem__((0, 0), 2.0), "pose 1 has a rotation part that is not orthonormal: R R\\^T is 4.0e\\+00 off"),
    (lambda M: M[:3, 0].neg_(), r"pose 1 has a rotation part that is a reflection \(determinant < 0\)"),
])
def test_refuses_a_pose_that_is_not_rigid_naming_it(change, match):
    pred = bare_predictor()
    bad = a_pose()
    change(bad)
    with pytest.raises(UserError, match=match) as err:
        pred.cameras_from_source(torch.stack([a_pose(), bad]), K, 128, 96)
    assert "rigid transforms" in str(err.value)


@pytest.mark.parametrize("row, col, value, match", [
    (2, 0, 0.1, r"K of pose 1 has the last row \[0.1, 0.0, 1.0\], not \[0, 0, 1\]"),
    (2, 2, 2.0, r"K of pose 1 has the last row"),
    (0, 1, 3.0, r"K of pose 1 has the skew K\[0,1\] = 3"),
    (0, 1, 0.01, r"K of pose 1 has the skew K\[0,1\] = 0.01"),  # 1e-4 of fx: more than rounding, dropped unsaid
    (1, 0, 1e-9, r"K of pose 1 has the skew .*K\[1,0\] = 1e-09"),
    (0, 0, 0.0, "K of pose 1 has the focal lengths 0 / 90 px: they must be positive and finite"),
    (1, 1, -90.0, "K of pose 1 has the focal lengths 100 / -90 px"),
    (0, 0, float("nan"), "K of pose 1 has the focal lengths nan / 90 px"),
    (1, 1, float("inf"), "K of pose 1 has the focal lengths 100 / inf px"),
    (0, 0, 1e39, "K of pose 1 has the focal lengths 1e[+]39 / 90 px: they must be positive and finite in float32"),
    (0, 2, float("nan"), "K of pose 1 has the principal point nan, 48: it must be finite"),
])
def test_refuses_intrinsics_the_renderer_would_not_take_as_given(row, col, value, match):
    pred = bare_predictor()
    bad = K.clone()
    bad[row, col] = value
    poses = torch.stack([a_pose(), a_pose()])
    with pytest.raises(UserError, match=match):
        pred.cameras_from_source(poses, torch.stack([K, bad]), 128, 96)
    with pytest.raises(UserError, match=match.replace("K of pose 1", "K")):  # one K for both poses
        pred.cameras_from_source(poses, bad, 128, 96)


def test_principal_point_outside_counts_the_edges_as_inside():
    """The one condition ``train``'s scene check and the ``Predictor`` share: the image's edges are inside, a point
    a hair beyond any edge is outside, per camera of a batch."""
    from uncertsplat.types import intrinsics_size_guess, principal_point_outside

    def K(cx, cy):
        return torch.tensor([[100.0, 0.0, cx], [0.0, 100.0, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
    Ks = torch.stack([K(0, 0), K(320, 240), K(160, 120), K(-1e-9, 5), K(320.001, 5), K(5, 240.5), K(5, -3)])
    assert principal_point_outside(Ks, 320, 240).tolist() == [False, False, False, True, True, True, True]
    assert intrinsics_size_guess(2016, 1512).endswith("about 4032x3024 pixels")
    assert intrinsics_size_guess(-5, 100) == ""  # no size to suggest from a negative point


def test_refuses_a_principal_point_outside_the_image_unless_told():
    """A 4032x3024 photo's K with a 320x240 size rendered a 12x-zoomed, off-centre patch whose std looked more
    certain than the right camera's, without a word (``train`` refuses the same mistake)."""
    pred = bare_predictor()
    full = torch.tensor([[3000.0, 0.0, 2016.0], [0.0, 3000.0, 1512.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    with pytest.raises(UserError, match=r"K has its principal point at \(2016, 1512\), outside the 320x240 image; the "
                                        r"intrinsics seem to belong to images of about 4032x3024 pixels") as err:
        pred.cameras_from_source(torch.stack([a_pose(), a_pose()]), full, 320, 240)
    assert "principal_point_outside=True" in err.value.hint
    cams = pred.cameras_from_source(a_pose(), full, 320, 240, principal_point_outside=True)  # a crop: accepted
    assert float(cams.K[0, 0, 2]) == 2016.0
    # on the border, or in the outer 5 %: a K twice the size given with halved width and height lands exactly on the
    # corner (a helper: a zoomed patch, std 0.069 against 0.076, median depth 8.5 against 4.0), refused as train
    # refuses it; a crop says so
    with pytest.raises(UserError, match=r"principal point at \(64, 48\), at the edge of the 64x48 image; the "
                                        r"intrinsics seem to belong to images of about 128x96"):
        pred.cameras_from_source(a_pose(), K, 64, 48)
    edge = K.clone()
    edge[0, 2], edge[1, 2] = 128.0, 48.0
    with pytest.raises(UserError, match=r"at \(128, 48\), at the edge of the 128x96 image\. "):
        pred.cameras_from_source(a_pose(), edge, 128, 96)
    pred.cameras_from_source(a_pose(), edge, 128, 96, principal_point_outside=True)
    inner = K.clone()
    inner[0, 2], inner[1, 2] = 0.06 * 128, 0.94 * 96
    pred.cameras_from_source(a_pose(), inner, 128, 96)  # off-centre, inside the outer 5 %: the user's to choose
    with pytest.raises(UserError, match="K of pose 1 has its principal point at"):
        pred.cameras_from_source(torch.stack([a_pose(), a_pose()]), torch.stack([K, full]), 128, 96)


def test_refuses_width_and_height_swapped_unless_told():
    """A 640x480 camera's K given with width=480, height=640 (an image array's shape is (height, width)) put the
    principal point inside, off-centre, and rendered a shifted view of the pose without a word."""
    pred = bare_predictor()
    vga = torch.tensor([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    with pytest.raises(UserError, match=r"K has its principal point at \(320, 240\): the centre of a 640x480 image, far "
                                        r"off the centre of the 480x640 one given \(width and height swapped") as err:
        pred.cameras_from_source(torch.stack([a_pose(), a_pose()]), vga, 480, 640)
    assert "Pass width=640, height=480" in err.value.hint and "principal_point_outside=True" in err.value.hint
    pred.cameras_from_source(a_pose(), vga, 640, 480)
    pred.cameras_from_source(a_pose(), vga, 480, 640, principal_point_outside=True)  # a crop there: the user's call
    hd = torch.tensor([[1000.0, 0.0, 959.5], [0.0, 1000.0, 539.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    with pytest.raises(UserError, match="K of pose 0 has its principal point at \\(959.5, 539.5\\): the centre of a "
                                        "1920x1080 image"):
        pred.cameras_from_source(a_pose(), hd, 1080, 1920)
    # a square image, or a point near both centres (a nearly square image), is not told anything
    sq = torch.tensor([[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    pred.cameras_from_source(a_pose(), sq, 100, 100)
    near = torch.tensor([[100.0, 0.0, 50.0], [0.0, 100.0, 51.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    pred.cameras_from_source(a_pose(), near, 102, 100)


def test_poses_and_intrinsics_as_robots_hold_them():
    """Intrinsics that need grad warned from inside and kept their grad in ``Cameras.K``; a list of pose tensors ended
    in torch's own wording; cameras without names gave a prediction without names."""
    import warnings

    pred = bare_predictor()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cams = pred.cameras_from_source(a_pose(), K.clone().float().requires_grad_(), 128, 96)
    assert not cams.K.requires_grad
    listed = pred.cameras_from_source([a_pose(), a_pose().float()], [K, K], 128, 96)
    torch.testing.assert_close(listed.cam_from_world,
                               pred.cameras_from_source(torch.stack([a_pose()] * 2), K, 128, 96).cam_from_world)
    with warnings.catch_warnings():  # a list of arrays: torch warns that it is very slow
        warnings.simplefilter("error")
        pred.cameras_from_source([a_pose().numpy()] * 3, K.numpy(), 128, 96)


def test_half_precision_poses_are_told_to_pass_float32():
    pose = a_pose().to(torch.float16)
    with pytest.raises(UserError, match="the poses are float16, whose 2-3 significant digits cannot hold a rotation"):
        bare_predictor().cameras_from_source(pose, K, 128, 96)
    bare_predictor().cameras_from_source(a_pose().float(), K, 128, 96)  # the pose in float32 is taken


def test_refuses_sizes_and_counts_that_are_not_whole_numbers():
    pred = bare_predictor()
    with pytest.raises(UserError, match="width must be a whole number, got 320.7"):
        pred.cameras_from_source(a_pose(), K, 320.7, 240)
    with pytest.raises(UserError, match="height must be 1 or more, got 0"):
        pred.cameras_from_source(a_pose(), K, 320, 0)
    with pytest.raises(UserError, match="width must be a whole number, got np.float32"):
        pred.cameras_from_source(a_pose(), K, np.float32(320.5), 240)
    with pytest.raises(UserError, match="width must be a whole number, got '320'"):
        pred.cameras_from_source(a_pose(), K, "320", 240)
    # whole sizes as camera-info arrays and tensors hold them (float32 was called "not whole")
    for w, h in ((np.float32(128.0), np.float64(96.0)), (torch.tensor(128.0), torch.tensor(96, dtype=torch.int16))):
        cams = pred.cameras_from_source(a_pose(), K, w, h)
        assert (cams.width, cams.height) == (128, 96)
    with pytest.raises(UserError, match="num_samples must be a whole number, got 2.7"):
        pred.predict(cams, num_samples=2.7)
    with pytest.raises(UserError, match="num_samples must be 1 or more, got 0"):
        pred.predict(cams, num_samples=0)
    with pytest.raises(UserError, match=r"seed must be at most 4294967295 \(2\*\*32 - 1\), got 1180591620717411303424"):
        pred.predict(cams, seed=2**70)
    with pytest.raises(UserError, match=r"seed must be at most 4294967295 \(2\*\*32 - 1\), got 4294967296"):
        pred.predict(cams, seed=2**32)  # (the CPU generator keeps the low 32 bits: it would be seed 0's maps)
    with pytest.raises(UserError, match="seed must be 0 or more, got -1"):
        pred.predict(cams, seed=-1)
    with pytest.raises(UserError, match="seed must be a whole number, got 1.5"):
        pred.predict(cams, seed=1.5)


def test_predict_says_what_to_pass_for_a_matrix():
    pred = bare_predictor()
    for wrong in (a_pose().numpy(), a_pose(), [a_pose()]):
        with pytest.raises(TypeError, match="predict takes a Cameras batch, got .*cameras_from_source"):
            pred.predict(wrong)


def test_predict_takes_the_configs_seed_and_samples_by_default(monkeypatch):
    """``predict()`` after ``evaluate --seed 3`` is evaluate's maps: the seed defaults to the config's, not 0."""
    pred = bare_predictor()
    seen = []
    monkeypatch.setattr(Predictor, "_predict", lambda self, cams, k, seed, terms=False: seen.append((k, seed)))
    cams = Cameras(torch.eye(4)[None], K.float()[None], 128, 96)
    pred.predict(cams)
    pred.predict(cams, num_samples=np.int64(2), seed=0)
    assert seen == [(3, 4), (2, 0)]


def test_the_interval_reads_the_std_as_the_student_ts_standard_deviation():
    """``rgb_std`` is the t's standard deviation: scipy's ``scale`` is std * sqrt((dof - 2) / dof); the interval is
    around the clamped mean that evaluate scores, and ``calibrated`` multiplies the std by the fitted factor."""
    stats = pytest.importorskip("scipy.stats")
    from uncertsplat.predict import Prediction

    mean = torch.tensor([0.2, 0.5, 1.3]).reshape(1, 1, 1, 3)
    std = torch.tensor([0.01, 0.05, 0.1]).reshape(1, 1, 1, 3)
    zero = torch.zeros(1, 1, 1, 1)
    pred = Prediction(mean, std, zero, zero, zero + 1, std_factor=0.8, dof=3.5, depth_to_source=1.0,
                      image_names=("a",))
    lower, upper = pred.interval(0.9)
    scale = std.double() * math.sqrt((3.5 - 2) / 3.5)
    lo, hi = stats.t.interval(0.9, 3.5, loc=mean.double().clamp(0, 1).numpy(), scale=scale.numpy())
    np.testing.assert_allclose(lower.numpy(), lo, rtol=0, atol=1e-6)
    np.testing.assert_allclose(upper.numpy(), hi, rtol=0, atol=1e-6)
    lower_c, upper_c = pred.interval(0.9, calibrated=True)
    torch.testing.assert_close(upper_c - lower_c, 0.8 * (upper - lower))
    gauss = Prediction(mean, std, zero, zero, zero + 1, std_factor=None, dof=None, depth_to_source=1.0,
                       image_names=("a",))
    lower_g, _ = gauss.interval(0.9)
    np.testing.assert_allclose(lower_g.numpy(), stats.norm.interval(0.9, loc=mean.clamp(0, 1).numpy(),
                                                                    scale=std.numpy())[0], rtol=0, atol=1e-6)
    with pytest.raises(UserError, match="no fitted std factor"):
        gauss.interval(0.9, calibrated=True)
    with pytest.raises(ValueError, match="probability must be in"):
        pred.interval(1.5)
    # a percentage (95 for 95 %) was told only the range
    with pytest.raises(ValueError, match=r"got 95.0 \(a probability, not a percentage: 0.95 for a 95 % interval\)"):
        pred.interval(95)


def test_load_names_a_file_given_for_the_run_folder(tmp_path):
    (tmp_path / "config.json").write_text("{}")
    with pytest.raises(UserError, match="takes a run folder, not a file in it") as err:
        Predictor.load(tmp_path / "config.json")
    assert str(tmp_path) in err.value.hint
    # a folder that is not there is said as the commands say it (it read "config.json is missing")
    with pytest.raises(UserError, match="run folder not found"):
        Predictor.load(tmp_path / "nope")


def test_load_reads_a_leading_tilde_as_the_home_folder(monkeypatch, tmp_path):
    """``Predictor.load("~/runs/x")`` said "run folder not found" of a run that was there: ``~`` is the home folder,
    as a shell reads it (and as the TOML files' paths are read)."""
    (tmp_path / "runs" / "x").mkdir(parents=True)
    monkeypatch.setenv("HOME", str(tmp_path))
    seen = []
    monkeypatch.setattr(Predictor, "_load", classmethod(lambda cls, run, device, cfg, evaluation: seen.append(run)))
    Predictor.load("~/runs/x", "cpu")
    assert seen == [tmp_path / "runs" / "x"]


def test_names_as_bytes_are_refused_not_read_as_numbers():
    """``names=b"ab"`` for two poses was iterated as the whole numbers 97 and 98, which names take as texts: the maps
    were named "97" and "98" without a word."""
    pred = bare_predictor()
    M = a_pose().numpy()
    with pytest.raises(UserError, match="names must be texts, one per pose, got bytes"):
        pred.cameras_from_source(np.stack([M, M]), K, 128, 96, names=b"ab")


def test_load_of_an_unknown_users_home_folder_says_the_run_is_not_found():
    """``~nosuchuser/run`` ended in pathlib's RuntimeError ("Could not determine home directory") once a leading ``~``
    was expanded: no such home folder is no such run folder."""
    with pytest.raises(UserError, match="run folder not found"):
        Predictor.load("~nosuchuser_of_uncertsplat/run", "cpu")


def test_cameras_built_by_hand_are_checked_before_the_renderer_sees_them(monkeypatch):
    """A ``Cameras`` of width 0, -5 or 1.5 failed deep inside torch (or ctypes), a NaN pose gave NaN maps without a
    word; a whole float size (320.0) is taken as an int."""
    pred = bare_predictor()
    seen = []
    monkeypatch.setattr(Predictor, "_predict", lambda self, cams, k, seed, terms=False: seen.append((cams.width, cams.height)))
    pose, k = torch.eye(4)[None], K.float()[None]
    for w, match in ((0, "width must be 1 or more, got 0"), (-5, "width must be 1 or more, got -5"),
                     (1.5, "width must be a whole number, got 1.5")):
        with pytest.raises(UserError, match=f"the cameras' {match}"):
            pred.predict(Cameras(pose, k, w, 96))
    nan = pose.clone()
    nan[0, 0, 3] = float("nan")
    with pytest.raises(UserError, match=r"camera 0 \(v\): its pose \(cam_from_world\) is not finite.*cameras_from_source"):
        pred.predict(Cameras(nan, k, 128, 96, ("v",)))
    bad = k.clone()
    bad[0, 0, 0] = 0.0
    with pytest.raises(UserError, match="camera 0: its focal lengths are not positive"):
        pred.predict(Cameras(pose, bad, 128, 96))
    bad[0, 0, 0] = float("inf")
    with pytest.raises(UserError, match="camera 0: its K is not finite"):
        pred.predict(Cameras(pose, bad, 128, 96))
    assert seen == []
    pred.predict(Cameras(pose, k, 128.0, np.float32(96)))
    assert seen == [(128, 96)] and all(type(v) is int for v in seen[0])


@pytest.mark.parametrize("change, match", [
    # a [3,4] padded with a row of zeros: torch's "linalg.inv: ... singular" from the view-consistency term
    (lambda M: M[3].zero_(), r"its pose \(cam_from_world\) has the last row \[0.0, 0.0, 0.0, 0.0\], not \[0, 0, 0, 1\]"),
    # a sim(3) pose: rendered other maps without a word
    (lambda M: M[:3, :3].mul_(2.0), "its pose .* rotation part that is not orthonormal: R R\\^T is 3.0e\\+00 off .*1e-3"),
    (lambda M: M[:3, 0].neg_(), r"its pose .* rotation part that is a reflection"),
])
def test_cameras_built_by_hand_that_are_not_rigid_are_refused(monkeypatch, change, match):
    pred = bare_predictor()
    seen = []
    monkeypatch.setattr(Predictor, "_predict", lambda self, cams, k, seed, terms=False: seen.append(len(cams)))
    bad = a_pose()
    change(bad)
    poses = torch.stack([a_pose(), bad]).float()
    with pytest.raises(UserError, match=r"camera 1 \(mine\): " + match):
        pred.predict(Cameras(poses, K.float().expand(2, 3, 3).clone(), 128, 96, ("ok", "mine")))
    # what the scene loaders take (a transforms.json rotation within 1e-3) is taken here too: the run's own cameras
    near = a_pose()
    near[:3, :3] *= 1.0 + 2e-4
    pred.predict(Cameras(torch.stack([a_pose(), near]).float(), K.float().expand(2, 3, 3).clone(), 128, 96))
    assert seen == [2]


def test_arrays_of_the_other_byte_order_read_only_or_not_arrays():
    """A big-endian array was refused as "not a tensor or array", a read-only one (np.broadcast_to) made torch warn,
    and something that is no array raised a TypeError where the docstring (and seen_free) says UserError."""
    import warnings

    pred = bare_predictor()
    M = a_pose().numpy()
    expected = pred.cameras_from_source(M, K, 128, 96)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for poses, Ks in ((M.astype(">f8"), K.numpy().astype(">f4")),
                          (np.broadcast_to(M, (1, 4, 4)), np.broadcast_to(K.numpy(), (1, 3, 3)))):
            got = pred.cameras_from_source(poses, Ks, 128, 96)
            torch.testing.assert_close(got.cam_from_world, expected.cam_from_world, atol=0, rtol=0)
            torch.testing.assert_close(got.K, expected.K, atol=0, rtol=0)
    with pytest.raises(UserError, match="cam_from_source must be a tensor or array of poses"):
        pred.cameras_from_source("abc", K, 128, 96)
    with pytest.raises(UserError, match="K must be a tensor or array"):
        pred.cameras_from_source(M, {"fx": 1}, 128, 96)


def test_load_takes_the_config_as_a_dict_and_names_a_bad_key(monkeypatch, tmp_path):
    """``cfg={"num_samples": 2}`` was an AttributeError ('dict' object has no attribute 'model_dump') from deep inside
    the load: a dict of ``EvalConfig``'s keys is taken, a bad key named as ``--set`` names it."""
    seen = []
    monkeypatch.setattr(Predictor, "_load", classmethod(lambda cls, run, device, cfg, evaluation: seen.append(cfg)))
    Predictor.load(tmp_path, "cpu", cfg={"num_samples": 2})
    assert seen == [EvalConfig(num_samples=2)]
    Predictor.load(tmp_path, "cpu", cfg=EvalConfig(num_samples=3))
    assert seen[-1] == EvalConfig(num_samples=3)
    with pytest.raises(UserError, match=r"invalid configuration in Predictor.load's cfg: num_sample: unknown key "
                                        r"\(did you mean num_samples\?\)"):
        Predictor.load(tmp_path, "cpu", cfg={"num_sample": 2})
    with pytest.raises(UserError, match="num_samples: Input should be greater than or equal to 1"):
        Predictor.load(tmp_path, "cpu", cfg={"num_samples": 0})
    with pytest.raises(TypeError, match="cfg must be an uncertsplat.config.EvalConfig .*got int"):
        Predictor.load(tmp_path, "cpu", cfg=4)
    assert len(seen) == 2
    # over the run's evaluation's settings, as `evaluate --set` changes one (with the defaults under it, the
    # predictive was another than the one evaluate scored)
    (tmp_path / "eval").mkdir()
    (tmp_path / "eval" / "config.json").write_text(EvalConfig(seed=7, residual_views=5).model_dump_json())
    Predictor.load(tmp_path, "cpu", cfg={"num_samples": 2})
    assert seen[-1] == EvalConfig(seed=7, residual_views=5, num_samples=2)
    # an evaluation from before colour_covariance existed used the diagonal colour posterior (its predictive.pt holds
    # it): read so, where the default is the block
    old = json.loads(EvalConfig(seed=7).model_dump_json())
    del old["colour_covariance"]
    (tmp_path / "eval" / "config.json").write_text(json.dumps(old))
    Predictor.load(tmp_path, "cpu")
    assert seen[-1] == EvalConfig(seed=7, colour_covariance="diagonal") and EvalConfig().colour_covariance == "block"


def test_names_none_numbers_and_numpy_texts():
    """``names=None`` was "'NoneType' object is not iterable"; frame numbers or numpy's texts became the maps' names
    as given (ints, ``np.str_``); a None among them is named by its place."""
    pred = bare_predictor()
    two = torch.stack([a_pose(), a_pose()])
    assert pred.cameras_from_source(two, K, 128, 96, names=None).image_names == ("pose_0", "pose_1")
    got = pred.cameras_from_source(two, K, 128, 96, names=[7, np.int64(8)]).image_names
    assert got == ("7", "8") and all(type(n) is str for n in got)
    got = pred.cameras_from_source(two, K, 128, 96, names=np.array(["a", "b"])).image_names
    assert got == ("a", "b") and all(type(n) is str for n in got)
    with pytest.raises(UserError, match="name 1 must be a text .*got None"):
        pred.cameras_from_source(two, K, 128, 96, names=("a", None))
    with pytest.raises(UserError, match="names must be texts, one per pose, got float"):
        pred.cameras_from_source(two, K, 128, 96, names=1.5)


def test_seen_free_takes_points_in_the_scenes_frame_through_the_similarity():
    """``seen_free(points)`` (source frame) tests x_world = s x_source + t, the normalisation a pose goes through
    (``cameras_from_source``); ``frame="world"`` passes them as given."""
    from types import SimpleNamespace

    pred = bare_predictor(scale=0.5, shift=(1.0, -2.0, 3.0))
    T = pred._world_from_source
    asked = []

    def free(pts):
        asked.append(pts.double())
        return pts[:, 0] > 0

    pred._sampler = SimpleNamespace(consistency=SimpleNamespace(seen_free=free))
    x = torch.tensor([[1.0, 2.0, 3.0], [-4.0, 0.5, 2.0]], dtype=torch.float64)
    got = pred.seen_free(x)
    homogeneous = torch.cat([x, torch.ones(2, 1, dtype=torch.float64)], 1)
    world = (T @ homogeneous.T).T[:, :3]
    torch.testing.assert_close(asked[0], world, atol=1e-6, rtol=0)
    assert got.tolist() == (world[:, 0] > 0).tolist()
    pred.seen_free(x, frame="world")
    torch.testing.assert_close(asked[1], x, atol=1e-6, rtol=0)
    torch.testing.assert_close(pred.seen_free(x[0]), got[:1])  # one point as [3]


def test_a_pose_that_sees_none_of_the_model_gets_a_note_on_its_convention(capsys):
    """A pose in another convention (OpenGL axes given as OpenCV's, camera-to-world as world-to-camera) rendered maps
    that look like an honest, uncertain view, without a word: a pose that sees under a tenth of what the training
    views see of the model's Gaussians is named, with the fraction and the two options to check."""
    from types import SimpleNamespace

    pred = bare_predictor(scale=1.0, shift=(0.0, 0.0, 0.0))
    g = torch.Generator().manual_seed(0)
    means = torch.rand(500, 3, generator=g) * torch.tensor([2.0, 2.0, 2.0]) + torch.tensor([-1.0, -1.0, 3.0])
    K1 = torch.tensor([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])
    train = Cameras(torch.eye(4)[None], K1[None], 64, 48, ("train_0",))
    pred.loaded = SimpleNamespace(model=SimpleNamespace(params={"means": means}))
    pred.scene = SimpleNamespace(split={"train": [0]}, cameras=train)
    pred._train_seen = None
    ahead = torch.eye(4, dtype=torch.float64)
    cams = pred.cameras_from_source(ahead, K1, 64, 48, ("ahead",))
    assert len(cams) == 1 and "see almost none" not in capsys.readouterr().err
    # the same camera as an OpenGL pose given as OpenCV's: it looks backward, away from every Gaussian
    gl = ahead.clone()
    gl[:3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    pred.cameras_from_source(torch.stack([ahead, gl]), K1, 64, 48, ("ahead", "mixed_up"))
    err = " ".join(capsys.readouterr().err.split())
    assert "1 of 2 pose(s) see almost none of the model (mixed_up 0.0 % of its Gaussians in view" in err
    assert 'transform="world_from_cam"' in err and 'axes="opengl"' in err
    # read with its own convention, the pose is the camera that sees them: no note
    pred.cameras_from_source(gl, K1, 64, 48, ("gl",), axes="opengl")
    assert "see almost none" not in capsys.readouterr().err


def test_a_blender_scenes_own_cameras_at_the_loaders_limit_pass(monkeypatch, tmp_path):
    """The loader takes a transforms.json pose whose R^T R (camera-to-world) is within 1e-3 of the identity; predict
    measured R R^T of its inverse, (R^T R)^-1, a little further off: a run's own camera trained and was refused."""
    import json

    from uncertsplat.config import SceneConfig
    from uncertsplat.io.images import write_png
    from uncertsplat.sfm.scene import load_scene

    frames = []
    for i in range(3):
        write_png(tmp_path / "train" / f"v{i}.png", np.full((6, 8, 3), 0.5, np.float32))
        c2w = np.eye(4)
        c2w[0, 3], c2w[2, 3] = 0.1 * i, 3.0
        if i == 1:
            c2w[:3, 0] *= math.sqrt(1.0 - 0.9995e-3)  # R^T R 0.9995e-3 off: trains
        frames.append({"file_path": f"./train/v{i}", "transform_matrix": c2w.tolist()})
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}))
    scene = load_scene(tmp_path, SceneConfig())
    pred = bare_predictor()
    seen = []
    monkeypatch.setattr(Predictor, "_predict", lambda self, cams, k, seed, terms=False: seen.append(len(cams)))
    pred.predict(scene.cameras)
    assert seen == [3]
    # a scale past the limit either way is still refused
    bad = scene.cameras.cam_from_world.clone()
    bad[1, :3, :3] *= 1.01
    with pytest.raises(UserError, match="not orthonormal"):
        pred.predict(Cameras(bad, scene.cameras.K, scene.cameras.width, scene.cameras.height))


def test_a_batchs_maps_and_terms_are_joined_without_holding_every_view_twice(monkeypatch):
    """``predict`` joins each view's maps (and with ``terms`` each part's) into the batch's: a view's piece of a map
    is let go once that map is joined, so that a large batch peaks at about what it returns plus one map, not twice
    what it returns (every view's pieces alive until the last map was joined: 3.4 GB for 1.7 GB returned with the
    terms). Per-view pieces and joined maps alive are counted at each join (stubbed renders)."""
    import types
    import weakref

    import uncertsplat.eval.engine as engine
    import uncertsplat.uncertainty.mc as mc

    H = W = 8
    pieces: list = []  # weakrefs to every per-view tensor handed out
    joined: list = []  # weakrefs to every joined tensor
    peak = [0]

    def alive(refs):
        return sum(t.numel() for t in (r() for r in refs) if t is not None)

    def fake_mc_render(sample_fn, render_fn, cam, k, gen, terms=False, **kw):
        def z(c):
            t = torch.rand(1, H, W, c)
            pieces.append(weakref.ref(t))
            return t

        return types.SimpleNamespace(
            rgb_mean=z(3), rgb_std=z(3), depth_mean=z(1), depth_std=z(1), alpha_mean=z(1),
            rgb_terms={f"r{i}": z(1) for i in range(4)} if terms else None,
            depth_terms={f"d{i}": z(1) for i in range(3)} if terms else None), None

    real_cat = torch.cat

    def counting_cat(tensors, *args, **kwargs):
        peak[0] = max(peak[0], alive(pieces) + alive(joined))
        out = real_cat(tensors, *args, **kwargs)
        joined.append(weakref.ref(out))
        return out

    monkeypatch.setattr(mc, "mc_render", fake_mc_render)
    monkeypatch.setattr(engine, "predictive_terms", lambda *a, **k: {})
    pred = bare_predictor()
    pred._sampler = types.SimpleNamespace(sample_fn=None, render_fn=None)
    pred.scene = types.SimpleNamespace(cameras=types.SimpleNamespace(image_names=()))
    pred.scale, pred.std_factor, pred.dof = 0.5, None, None
    pred._free_space = lambda: types.SimpleNamespace(seen_free=lambda c: torch.ones(len(c), dtype=torch.bool))
    n = 6
    cams = Cameras(torch.eye(4)[None].repeat(n, 1, 1), K.float()[None].repeat(n, 1, 1), W, H)
    for terms in (False, True):
        pieces.clear(), joined.clear()
        peak[0] = 0
        monkeypatch.setattr(torch, "cat", counting_cat)
        out = pred.predict(cams, terms=terms)
        monkeypatch.setattr(torch, "cat", real_cat)
        maps = [out.rgb_mean, out.rgb_std, out.depth_mean, out.depth_std, out.alpha]
        maps += list((out.rgb_terms or {}).values()) + list((out.depth_terms or {}).values())
        returned = sum(m.numel() for m in maps)
        assert returned == n * H * W * (9 + 7 * terms)
        # at most what is returned and one map of three channels (the pieces of the one being joined)
        assert peak[0] <= returned + n * H * W * 3, (terms, peak[0], returned)


def test_evaluation_config_reads_the_runs_evaluation_and_falls_back_to_the_defaults(tmp_path):
    """``evaluation_config``: RUN/eval/config.json as written (one from before ``colour_covariance`` existed is the
    diagonal form it used); the defaults where there is none, or it is damaged or of a newer version."""
    from uncertsplat.stages.predictive_cache import evaluation_config

    assert evaluation_config(tmp_path) == EvalConfig()
    (tmp_path / "eval").mkdir()
    path = tmp_path / "eval" / "config.json"
    path.write_text(json.dumps({"num_samples": 4}))
    assert evaluation_config(tmp_path) == EvalConfig(num_samples=4, colour_covariance="diagonal")
    path.write_text(json.dumps({"num_samples": 4, "colour_covariance": "block"}))
    assert evaluation_config(tmp_path) == EvalConfig(num_samples=4, colour_covariance="block")
    for damaged in ('{"num_samples": "many"}', '{"no_such_setting": 1}', "{not json", "[1, 2]"):
        path.write_text(damaged)
        assert evaluation_config(tmp_path) == EvalConfig(), damaged


def test_the_scene_digest_leaves_out_where_the_scene_lies_alone(tmp_path):
    """``_scene_digest``: scene.json without where the scene lies (``SCENE_LOCATION``); of the file's bytes where it
    is not a JSON object (damaged, or a list); None without the file."""
    import hashlib

    from uncertsplat.stages.predictive_cache import _scene_digest

    assert _scene_digest(tmp_path) is None
    path = tmp_path / "scene.json"
    base = {"train": ["a"], "source": {"kind": "colmap", "path": "/x", "model": "/x/sparse/0"}}
    path.write_text(json.dumps({**base, "scene": "/x", "scene_from_run": "../x"}))
    here = _scene_digest(tmp_path)
    path.write_text(json.dumps({**base, "scene": "/y", "scene_from_run": "../y",
                                "source": {"kind": "colmap", "path": "/y", "model": "/y/sparse/0"}}))
    assert _scene_digest(tmp_path) == here, "moved: the same digest"
    path.write_text(json.dumps({**base, "source": {"kind": "nerfstudio", "path": "/x", "model": "/x/sparse/0"}}))
    assert _scene_digest(tmp_path) != here, "what the run was trained on is kept"
    for raw in (b"[1, 2]", b"{damaged", b"\xff"):
        path.write_bytes(raw)
        assert _scene_digest(tmp_path) == hashlib.sha256(raw).hexdigest(), raw


def test_a_predictive_is_not_rekeyed_for_a_run_with_other_digests(monkeypatch, tmp_path):
    """``rekeyed_predictive``: the target run's digests name other files (its photos have masks, the source's not):
    the source's fit does not describe it, and nothing is copied; the same names are rekeyed."""
    from uncertsplat.io.checkpoints import decode, encode
    from uncertsplat.stages import predictive_cache as pc
    from uncertsplat.stages import residual_cache

    digests = {"model": "m", "config": "c", "scene": "s"}
    parts = {**digests, "settings": {}, "fit": 1}
    data = encode({"format": pc.FORMAT, "key": pc._key(parts), "parts": json.dumps(parts, sort_keys=True)})
    target = {"source": digests, "run": {**digests, "scene": "t"}}
    monkeypatch.setattr(residual_cache, "_model_of", lambda run, model: run)
    monkeypatch.setattr(pc, "_digests", lambda run: (target[run], target[run]))
    assert json.loads(decode(pc.rekeyed_predictive(data, "source", "run", "m.ply"))["parts"])["scene"] == "t"
    target["run"] = {**digests, "masks": "k"}
    assert pc.rekeyed_predictive(data, "source", "run", "m.ply") is None
