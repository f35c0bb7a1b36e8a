"""Unit tests of the reconstruct building blocks (no feature matching or mapping here: fast)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from uncertsplat.config import ReconstructConfig
from uncertsplat.errors import UserError
from uncertsplat.sfm import reconstruct as sfm
from uncertsplat.sfm.report import (
    REPORT_NAME,
    ReconstructReport,
    load_report,
    require_successful,
    write_report,
)
from uncertsplat.stages import reconstruct as stage


def write_image(path: Path, width: int = 32, height: int = 24, orientation: int | None = None, seed: int = 0):
    """A random RGB image; ``orientation`` sets the EXIF Orientation tag."""
    arr = np.random.default_rng(seed).integers(0, 255, (height, width, 3), dtype=np.uint8)
    spec = oiio.ImageSpec(width, height, 3, "uint8")
    if orientation is not None:
        spec.attribute("Orientation", orientation)
    out = oiio.ImageOutput.create(str(path))
    assert out is not None, oiio.geterror()
    out.open(str(path), spec)
    out.write_image(arr)
    out.close()
    return arr


# ------------------------------------------------------------------------------------------------ scan
def test_scan_accepts_mixed_case_extensions_and_ignores_the_rest(tmp_path):
    for i, name in enumerate(["a.JPG", "b.jpeg", "c.Png", "d.TIF", "e.tiff"]):
        write_image(tmp_path / name, seed=i)
    (tmp_path / "notes.txt").write_text("hello")
    (tmp_path / ".DS_Store").write_bytes(b"\0")
    (tmp_path / "nested").mkdir()
    write_image(tmp_path / "nested" / "f.jpg")
    scan = sfm.scan_photos(tmp_path)
    assert scan.names == ["a.JPG", "b.jpeg", "c.Png", "d.TIF", "e.tiff"]
    assert set(scan.ignored) == {"notes.txt", ".DS_Store", "nested/"}
    assert any("nested" in n for n in scan.notes)
    assert all((p.width, p.height) == (32, 24) for p in scan.photos)


def test_scan_empty_folder(tmp_path):
    with pytest.raises(UserError, match="empty"):
        sfm.scan_photos(tmp_path)


def test_scan_folder_without_photos(tmp_path):
    (tmp_path / "readme.txt").write_text("x")
    with pytest.raises(UserError, match="no JPEG, PNG or TIFF"):
        sfm.scan_photos(tmp_path)


def test_scan_missing_folder(tmp_path):
    with pytest.raises(UserError, match="not found"):
        sfm.scan_photos(tmp_path / "nope")


def test_scan_fewer_than_three_images(tmp_path):
    write_image(tmp_path / "a.jpg")
    write_image(tmp_path / "b.jpg")
    with pytest.raises(UserError, match="only 2 photo"):
        sfm.scan_photos(tmp_path)


def test_scan_names_a_broken_photo_before_counting(tmp_path):
    """One good photo and a text file named .jpg: the broken file is named, not just "only 2 photos"."""
    write_image(tmp_path / "a.jpg")
    (tmp_path / "b.jpg").write_bytes(b"not a photo")
    with pytest.raises(UserError, match=r"1 photo\(s\) cannot be read: b\.jpg"):
        sfm.scan_photos(tmp_path)


def test_scan_names_every_unreadable_file(tmp_path):
    for i in range(3):
        write_image(tmp_path / f"ok{i}.png", seed=i)
    (tmp_path / "broken.jpg").write_bytes(b"this is not a jpeg")
    (tmp_path / "empty.PNG").write_bytes(b"")
    with pytest.raises(UserError) as err:
        sfm.scan_photos(tmp_path)
    msg = str(err.value)
    assert "broken.jpg" in msg and "empty.PNG" in msg and "ok0.png" not in msg


@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_scan_names_a_photo_whose_pixels_end_early(tmp_path, ext):
    """A truncated file's header reads well; its pixels do not (COLMAP would fill them in without a word)."""
    for i in range(3):
        write_image(tmp_path / f"ok{i}{ext}", 64, 48, seed=i)
    write_image(tmp_path / f"cut{ext}", 64, 48, seed=9)
    data = (tmp_path / f"cut{ext}").read_bytes()
    (tmp_path / f"cut{ext}").write_bytes(data[: len(data) // 2])
    with pytest.raises(UserError) as err:
        sfm.scan_photos(tmp_path)
    msg = str(err.value)
    assert f"cut{ext}" in msg and "truncated" in msg and "ok0" not in msg


def test_scan_leaves_out_exact_copies_and_names_them(tmp_path):
    for i in range(4):
        write_image(tmp_path / f"p{i}.png", seed=i)
    (tmp_path / "p1_copy.png").write_bytes((tmp_path / "p1.png").read_bytes())
    (tmp_path / "z.png").write_bytes((tmp_path / "p3.png").read_bytes())
    write_image(tmp_path / "same_size_other_pixels.png", seed=7)  # the size of the others, not a copy
    scan = sfm.scan_photos(tmp_path)
    assert scan.names == ["p0.png", "p1.png", "p2.png", "p3.png", "same_size_other_pixels.png"]
    assert {"p1_copy.png", "z.png"} <= set(scan.ignored)
    assert any("p1_copy.png (= p1.png)" in n and "z.png (= p3.png)" in n for n in scan.notes)


@pytest.mark.parametrize("copy", ["IMG_4037 (1).jpg", "IMG_4037 - Copy.jpg", "IMG_4037 copy 2.jpg", "IMG_4037-copy.jpg",
                                  "Copy of IMG_4037.jpg", "Copy (2) of IMG_4037.jpg", "copy_of_IMG_4037.jpg"])
def test_of_a_photo_and_its_copy_the_original_name_is_kept(tmp_path, copy):
    """A file manager's copy ("IMG_4037 (1).jpg" sorts before "IMG_4037.jpg": a space before the dot) is the one
    left out, so the outputs carry the photo's own name."""
    for i in range(3):
        write_image(tmp_path / f"IMG_403{i}.jpg", seed=i)
    write_image(tmp_path / "IMG_4037.jpg", seed=5)
    (tmp_path / copy).write_bytes((tmp_path / "IMG_4037.jpg").read_bytes())
    scan = sfm.scan_photos(tmp_path)
    assert "IMG_4037.jpg" in scan.names and copy not in scan.names and copy in scan.ignored
    assert any(f"{copy} (= IMG_4037.jpg)" in n for n in scan.notes)


def test_scan_refuses_a_folder_of_copies(tmp_path):
    write_image(tmp_path / "a.png")
    for name in ("b.png", "c.png"):
        (tmp_path / name).write_bytes((tmp_path / "a.png").read_bytes())
    with pytest.raises(UserError, match="only 1 different photo"):
        sfm.scan_photos(tmp_path)


def test_scan_keeps_one_photo_per_name_stem(tmp_path):
    for i in range(3):
        write_image(tmp_path / f"IMG_{i}.jpg", seed=i)
    write_image(tmp_path / "IMG_1.png", seed=5)  # evaluate's maps of the two would share one file name
    scan = sfm.scan_photos(tmp_path)
    assert scan.names == ["IMG_0.jpg", "IMG_1.jpg", "IMG_2.jpg"]
    assert "IMG_1.png" in scan.ignored
    assert any("IMG_1.png (beside IMG_1.jpg)" in n for n in scan.notes)


def test_scan_notes_photos_with_an_alpha_channel(tmp_path):
    for i in range(3):
        write_image(tmp_path / f"p{i}.jpg", seed=i)
    spec = oiio.ImageSpec(32, 24, 4, "uint8")
    out = oiio.ImageOutput.create(str(tmp_path / "cutout.png"))
    out.open(str(tmp_path / "cutout.png"), spec)
    out.write_image(np.full((24, 32, 4), 128, dtype=np.uint8))
    out.close()
    scan = sfm.scan_photos(tmp_path)
    assert [p.name for p in scan.photos if p.alpha] == ["cutout.png"]
    assert any("alpha channel" in n and "cutout.png" in n for n in scan.notes)
    (tmp_path / "cutout.png").unlink()
    assert not any("alpha" in n for n in sfm.scan_photos(tmp_path).notes)


def test_a_broken_link_among_the_photos_is_named_as_one(tmp_path):
    for i in range(3):
        write_image(tmp_path / f"p{i}.jpg", seed=i)
    (tmp_path / "zz.jpg").symlink_to(tmp_path / "gone" / "zz.jpg")
    with pytest.raises(UserError, match=r"zz\.jpg \(a link to .*gone/zz\.jpg, which does not exist\)"):
        sfm.scan_photos(tmp_path)


def test_jpegs_saved_as_jfif_are_photos(tmp_path):
    """Windows browsers save JPEGs as .jfif (and some tools as .jpe): read as photos (COLMAP reads them too),
    not listed among the other files."""
    for i, ext in enumerate((".jfif", ".JFIF", ".jpe")):
        write_image(tmp_path / f"p{i}.jpg", seed=i)
        (tmp_path / f"p{i}.jpg").rename(tmp_path / f"p{i}{ext}")
    scan = sfm.scan_photos(tmp_path)
    assert scan.names == ["p0.jfif", "p1.JFIF", "p2.jpe"] and not scan.ignored


def test_scan_notes_grayscale_photos_among_colour_ones(tmp_path):
    """A grey photo (one channel, or one with alpha) among colour ones is named; a capture all in grey is not."""
    for i in range(3):
        write_image(tmp_path / f"p{i}.jpg", seed=i)
    for name, channels in (("grey.jpg", 1), ("grey_alpha.png", 2)):
        out = oiio.ImageOutput.create(str(tmp_path / name))
        out.open(str(tmp_path / name), oiio.ImageSpec(32, 24, channels, "uint8"))
        out.write_image(np.random.default_rng(channels).integers(0, 255, (24, 32, channels), dtype=np.uint8))
        out.close()
    scan = sfm.scan_photos(tmp_path)
    assert sorted(p.name for p in scan.photos if p.gray) == ["grey.jpg", "grey_alpha.png"]
    (note,) = [n for n in scan.notes if "grayscale" in n]
    assert note.startswith("2 photo(s) are grayscale among colour photos") and "grey.jpg, grey_alpha.png" in note
    for i in range(3):
        (tmp_path / f"p{i}.jpg").unlink()
    out = oiio.ImageOutput.create(str(tmp_path / "grey2.png"))
    out.open(str(tmp_path / "grey2.png"), oiio.ImageSpec(32, 24, 1, "uint8"))
    out.write_image(np.zeros((24, 32, 1), dtype=np.uint8))
    out.close()
    assert not any("grayscale" in n for n in sfm.scan_photos(tmp_path).notes)


def test_size_groups_and_exif_orientation(tmp_path):
    write_image(tmp_path / "a.jpg", 40, 30)
    write_image(tmp_path / "b.jpg", 40, 30, orientation=6)  # stored landscape, shown portrait
    write_image(tmp_path / "c.jpg", 30, 40)
    write_image(tmp_path / "d.jpg", 64, 48)
    scan = sfm.scan_photos(tmp_path)
    assert {p.name: p.orientation for p in scan.photos}["b.jpg"] == 6
    groups = scan.size_groups()
    assert groups == {(40, 30): ["a.jpg"], (30, 40): ["b.jpg", "c.jpg"], (64, 48): ["d.jpg"]}


def test_two_lenses_of_one_size_get_a_camera_each(tmp_path):
    """A phone's main and tele lens make photos of one size: one shared camera got a focal length between the two
    and a distortion of 0.71. The EXIF camera, lens and focal length tell them apart; photos of that size without
    EXIF join the most common lens; photos of one lens (or none named) stay one group per size. A digital zoom
    (EXIF DigitalZoomRatio above 1) is another focal length in pixels through the same lens: a group of its own."""
    def exif(path, model, focal, seed, zoom=None):
        a = np.random.default_rng(seed).integers(0, 255, (30, 40, 3), dtype=np.uint8)
        spec = oiio.ImageSpec(40, 30, 3, "uint8")
        if model:
            spec.attribute("Make", "Phone")
            spec.attribute("Model", model)
            spec.attribute("Exif:FocalLength", float(focal))
        if zoom is not None:
            spec.attribute("Exif:DigitalZoomRatio", float(zoom))
        out = oiio.ImageOutput.create(str(path))
        out.open(str(path), spec)
        out.write_image(a)
        out.close()

    for i, (model, focal) in enumerate([("A", 4.0), ("A", 4.0), ("A", 4.0), ("B", 5.0), ("B", 5.0), (None, 0)]):
        exif(tmp_path / f"p{i}.jpg", model, focal, i)
    write_image(tmp_path / "q.jpg", 64, 48)
    scan = sfm.scan_photos(tmp_path)
    assert {p.name: p.lens for p in scan.photos}["p3.jpg"] == "Phone B 5 mm"
    assert scan.camera_groups() == {(40, 30, "Phone A 4 mm"): ["p0.jpg", "p1.jpg", "p2.jpg", "p5.jpg"],
                                    (40, 30, "Phone B 5 mm"): ["p3.jpg", "p4.jpg"], (64, 48, ""): ["q.jpg"]}
    for i in (3, 4):
        exif(tmp_path / f"p{i}.jpg", "A", 4.0, i)
    assert sfm.scan_photos(tmp_path).camera_groups() == {
        (40, 30, ""): ["p0.jpg", "p1.jpg", "p2.jpg", "p3.jpg", "p4.jpg", "p5.jpg"], (64, 48, ""): ["q.jpg"]}
    exif(tmp_path / "p3.jpg", "A", 4.0, 3, zoom=1.0)  # no zoom written as 1 (or 0): the same lens
    exif(tmp_path / "p4.jpg", "A", 4.0, 4, zoom=2.0)
    assert sfm.scan_photos(tmp_path).camera_groups() == {
        (40, 30, "Phone A 4 mm"): ["p0.jpg", "p1.jpg", "p2.jpg", "p3.jpg", "p5.jpg"],
        (40, 30, "Phone A 4 mm digital zoom 2x"): ["p4.jpg"], (64, 48, ""): ["q.jpg"]}


def test_stage_inputs_rotates_by_exif(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    upright = write_image(photos / "a.png", 40, 30)
    stored = write_image(photos / "b.tif", 40, 30, orientation=6, seed=1)
    write_image(photos / "c.png", 40, 30, seed=2)
    scan = sfm.scan_photos(photos)
    folder, rotated = sfm.stage_inputs(scan, tmp_path / "staging")
    assert rotated == ["b.tif"] and folder == tmp_path / "staging"
    assert sorted(p.name for p in folder.iterdir()) == ["a.png", "b.tif", "c.png"]
    buf = oiio.ImageBuf(str(folder / "b.tif"))
    got = buf.get_pixels(oiio.UINT8)
    # orientation 6: the image must be rotated 90 degrees clockwise for display
    assert got.shape == (40, 30, 3)
    np.testing.assert_array_equal(got, np.rot90(stored, k=-1))
    assert buf.spec().get_int_attribute("Orientation", 1) == 1
    np.testing.assert_array_equal(oiio.ImageBuf(str(folder / "a.png")).get_pixels(oiio.UINT8), upright)


def test_stage_inputs_without_orientation_uses_the_photo_folder(tmp_path):
    for i in range(3):
        write_image(tmp_path / f"{i}.png", seed=i)
    scan = sfm.scan_photos(tmp_path)
    folder, rotated = sfm.stage_inputs(scan, tmp_path / "staging")
    assert folder == tmp_path and rotated == [] and not (tmp_path / "staging").exists()


# ---------------------------------------------------------------------------------------------- pairs
def test_exhaustive_pairs():
    names = [f"{i}.jpg" for i in range(6)]
    pairs = sfm.image_pairs(names, "exhaustive")
    assert len(pairs) == 15 and len(set(pairs)) == 15
    assert all(a < b for a, b in pairs)


def test_sequential_pairs_neighbours_and_quadratic_links():
    names = [f"{i:03d}.jpg" for i in range(100)]
    pairs = sfm.image_pairs(names, "sequential", overlap=5)
    assert len(pairs) == len(set(pairs))
    idx = {(int(a[:3]), int(b[:3])) for a, b in pairs}
    partners = sorted(j for i, j in idx if i == 10)
    assert partners == [11, 12, 13, 14, 15, 18, 26]  # 5 neighbours, then distances 8 and 16
    assert sorted(j for i, j in idx if i == 97) == [98, 99]
    assert all(j > i for i, j in idx)


def test_resolve_matcher():
    cfg = ReconstructConfig(exhaustive_max_images=10)
    assert sfm.resolve_matcher(cfg, 10) == "exhaustive"
    assert sfm.resolve_matcher(cfg, 11) == "sequential"
    assert sfm.resolve_matcher(ReconstructConfig(matcher="exhaustive", exhaustive_max_images=10), 500) == "exhaustive"


# ---------------------------------------------------------------------------------------------- align
def test_similarity_align_recovers_a_known_transform():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(30, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rot = q * np.sign(np.linalg.det(q))  # a proper rotation
    dst = 2.5 * src @ rot.T + np.array([1.0, -2.0, 0.5])
    s, r, t = sfm.similarity_align(src, dst)
    assert s == pytest.approx(2.5, rel=1e-9)
    np.testing.assert_allclose(r, rot, atol=1e-9)
    np.testing.assert_allclose(t, [1.0, -2.0, 0.5], atol=1e-9)


def test_similarity_align_never_returns_a_reflection():
    rng = np.random.default_rng(4)
    src = rng.normal(size=(20, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # a mirror image: best proper fit is not exact
    _, r, _ = sfm.similarity_align(src, dst)
    assert np.linalg.det(r) == pytest.approx(1.0)


# --------------------------------------------------------------------------------------------- report
def _report(**kw) -> ReconstructReport:
    base = dict(success=True, photos="/p", images_found=["a", "b", "c"], images_registered=["a", "b", "c"])
    base.update(kw)
    return ReconstructReport(**base)


def test_report_roundtrip_and_atomic_write(tmp_path):
    rep = _report(stage_seconds={"extract": 1.5}, cameras=[{"camera_id": 1, "model": "PINHOLE", "width": 4,
                                                             "height": 3, "params": [1, 1, 2, 1.5], "num_images": 3}])
    write_report(tmp_path, rep)
    assert [p.name for p in tmp_path.iterdir()] == [REPORT_NAME]  # no temp file left
    back = load_report(tmp_path)
    assert back == rep
    assert json.loads((tmp_path / REPORT_NAME).read_text(encoding="utf-8"))["success"] is True


def test_require_successful_refuses_a_failed_workspace(tmp_path):
    assert require_successful(tmp_path) is None  # a foreign workspace without a report is accepted
    write_report(tmp_path, _report(success=False, message="only 1/3 images registered",
                                   images_registered=["a"], images_unregistered=["b", "c"]))
    with pytest.raises(UserError, match="failed reconstruction"):
        require_successful(tmp_path)


def test_load_report_rejects_garbage(tmp_path):
    (tmp_path / REPORT_NAME).write_text("{not json")
    with pytest.raises(UserError, match="not valid JSON") as err:
        load_report(tmp_path)
    assert REPORT_NAME in str(err.value) and "uncertsplat reconstruct" in str(err.value)


# ------------------------------------------------------------------------------------------ workspace
def _photos(tmp_path: Path) -> Path:
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        write_image(photos / f"{i}.png", seed=i)
    return photos


def test_refuses_an_output_folder_with_other_files(tmp_path):
    photos = _photos(tmp_path)
    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / "thesis.docx").write_text("precious")
    with pytest.raises(UserError, match="--overwrite"):
        stage.run(photos, ws, ReconstructConfig())
    assert (ws / "thesis.docx").read_text(encoding="utf-8") == "precious"


def test_refuses_a_workspace_of_other_photos(tmp_path):
    photos = _photos(tmp_path)
    ws = tmp_path / "ws"
    write_report(ws, _report(photos=str(tmp_path / "elsewhere")))
    (ws / "sparse" / "0").mkdir(parents=True)
    with pytest.raises(UserError, match="other photos"):
        stage.run(photos, ws, ReconstructConfig())
    assert load_report(ws).photos == str(tmp_path / "elsewhere")  # untouched


def test_the_same_photos_copied_or_moved_reuse_their_workspace(tmp_path):
    """The photos' fingerprint is their names and contents: a copy that did not keep the modification times, in
    another folder, reuses the finished workspace (which then names the new folder); a workspace written with the
    earlier fingerprint (names, sizes, times) is still taken for the same photos; a changed photo is not."""
    import os
    import shutil

    from uncertsplat.sfm.reconstruct import scan_photos

    photos = _photos(tmp_path)
    scan = scan_photos(photos)
    ws = tmp_path / "ws"
    options = ReconstructConfig().model_dump(mode="json", exclude={"overwrite"})
    write_report(ws, _report(photos=str(photos.resolve()), inputs_fingerprint=scan.fingerprint(), options=options))
    (ws / "sparse" / "0").mkdir(parents=True)
    copy = tmp_path / "copy"
    shutil.copytree(photos, copy, copy_function=shutil.copyfile)  # (no times kept)
    for p in copy.iterdir():
        os.utime(p, (1e9, 1e9))
    assert scan_photos(copy).legacy_fingerprint() != scan.legacy_fingerprint()
    assert stage.run(copy, ws, ReconstructConfig()).success  # reused: nothing mapped
    assert load_report(ws).photos == str(copy.resolve())
    write_report(ws, _report(photos=str(photos.resolve()), inputs_fingerprint=scan.legacy_fingerprint(),
                             options=options))
    assert stage.run(photos, ws, ReconstructConfig()).success
    write_image(copy / "1.png", seed=7)
    with pytest.raises(UserError, match="other photos"):
        stage.run(copy, ws, ReconstructConfig())


def test_refuses_output_inside_or_around_the_photos(tmp_path):
    photos = _photos(tmp_path)
    with pytest.raises(UserError, match="inside the photo folder"):
        stage.run(photos, photos / "ws", ReconstructConfig(overwrite=True))
    with pytest.raises(UserError, match="contains the photo folder"):
        stage.run(photos, tmp_path, ReconstructConfig(overwrite=True))
    assert len(list(photos.iterdir())) == 3


def test_overwrite_removes_only_workspace_entries(tmp_path):
    photos = _photos(tmp_path)
    ws = tmp_path / "ws"
    (ws / "images").mkdir(parents=True)
    (ws / "images" / "old.png").write_bytes(b"x")
    (ws / "keep.txt").write_text("mine")
    write_report(ws, _report(photos=str(tmp_path / "elsewhere")))
    assert stage._prepare_workspace(photos, ws, ReconstructConfig(overwrite=True), ("fp",)) is None
    assert sorted(p.name for p in ws.iterdir()) == ["keep.txt"]


def _finished_workspace(tmp_path: Path) -> Path:
    ws = tmp_path / "ws"
    write_report(ws, _report(photos=str(tmp_path / "elsewhere")))
    for rel, data in (("sparse/0/points3D.bin", b"points"), ("images/a.png", b"image"), ("database.db", b"db"),
                      ("distorted/sparse/0/cameras.bin", b"cams"), ("masks/a.png.png", b"drawn by hand"),
                      ("notes.txt", b"mine")):
        (ws / rel).parent.mkdir(parents=True, exist_ok=True)
        (ws / rel).write_bytes(data)
    return ws


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != ".lock"}


def test_an_overwrite_stopped_puts_the_finished_workspace_back(tmp_path, monkeypatch, capsys):
    """--overwrite moved a finished workspace's files away only once the new one had finished: stopped (Ctrl-C, a
    failure) before, the workspace is as it was, hand-drawn masks and the user's files untouched, and the stopped
    run's report is kept beside it (a new user's failed retry had deleted the workspace a run was trained on)."""
    from uncertsplat.errors import Interrupted
    from uncertsplat.sfm.report import FAILED_REPORT_NAME, OVERWRITE_OLD, UNFINISHED

    photos = _photos(tmp_path)
    ws = _finished_workspace(tmp_path)
    before = _files(ws)

    def stop(*a, **k):
        (ws / "images").mkdir()
        (ws / "images" / "new.png").write_bytes(b"half made")
        raise KeyboardInterrupt

    monkeypatch.setattr(stage.sfm, "stage_inputs", stop)
    with pytest.raises(Interrupted, match="the workspace --overwrite was to replace is back as it was"):
        stage.run(photos, ws, ReconstructConfig(overwrite=True))
    after = _files(ws)
    assert ReconstructReport.model_validate_json(after.pop(FAILED_REPORT_NAME)).message == UNFINISHED
    assert after == before and not (ws / OVERWRITE_OLD).exists()
    assert "is back in" in capsys.readouterr().err


def test_an_overwrite_killed_is_undone_by_the_next_reconstruct(tmp_path, capsys):
    """Killed (no handler runs), an --overwrite leaves the old workspace aside and an unfinished new one: train names
    it and what puts it back; the next reconstruct of the folder puts the old one back before anything else, the new
    run's files gone (SQLite's -wal beside the database too: replayed into the old one, it emptied its matches)."""
    from uncertsplat.sfm.report import OVERWRITE_OLD, UNFINISHED, require_successful

    photos = _photos(tmp_path)
    ws = _finished_workspace(tmp_path)
    before = _files(ws)
    # as the killed run left it: its files moved aside, a new half-made workspace with its unfinished report
    assert stage._prepare_workspace(photos, ws, ReconstructConfig(overwrite=True), ("fp",)) is None
    assert (ws / OVERWRITE_OLD / "sparse").is_dir() and (ws / "masks" / "a.png.png").is_file()  # (not its own)
    write_report(ws, _report(photos=str(photos), success=False, message=UNFINISHED))
    (ws / "database.db").write_bytes(b"half made")
    (ws / "database.db-wal").write_bytes(b"the new run's log")
    (ws / "stereo").mkdir()
    with pytest.raises(UserError, match="--overwrite was stopped before it finished") as err:
        require_successful(ws)
    assert "puts back the workspace it was replacing before anything else" in err.value.hint
    with pytest.raises(UserError, match="other photos"):  # (the workspace back is of other photos: refused as ever)
        stage.run(photos, ws, ReconstructConfig())
    assert _files(ws) == before and not (ws / "stereo").exists() and not (ws / OVERWRITE_OLD).exists()
    assert "the workspace it was replacing is back" in capsys.readouterr().err


@pytest.mark.parametrize("moment", ["moving", "restoring", "restoring-twice", "finished"])
def test_an_overwrite_killed_at_any_moment_loses_nothing(tmp_path, moment):
    """A review killed --overwrite between its renames: put back after a kill while the old files went aside, the
    recovery deleted the ones still in place; killed while they came back, the next run deleted those back already;
    killed after the new workspace's report, the finished new workspace was thrown away for the old one."""
    from uncertsplat.sfm.report import OVERWRITE_MOVING, OVERWRITE_OLD, OVERWRITE_RESTORING, UNFINISHED

    photos = _photos(tmp_path)
    ws = _finished_workspace(tmp_path)
    before = _files(ws)
    assert stage._prepare_workspace(photos, ws, ReconstructConfig(overwrite=True), ("fp",)) is None
    old = ws / OVERWRITE_OLD
    if moment == "moving":  # killed with images/ and the report aside, the rest still in place
        (ws / OVERWRITE_MOVING).mkdir()
        for name in ("images", "reconstruct_report.json", "plan.json"):
            (old / name).rename(ws / OVERWRITE_MOVING / name)
        for name in [p.name for p in old.iterdir()]:
            (old / name).rename(ws / name)
        old.rmdir()
        assert stage._recover_overwrite(ws) == "restored"
        assert _files(ws) == before
        return
    write_report(ws, _report(photos=str(photos), success=moment == "finished", message="" if moment == "finished"
                             else UNFINISHED))
    (ws / "images").mkdir()
    (ws / "images" / "new.png").write_bytes(b"new")
    if moment == "finished":  # killed between the new report and dropping the old files: the new one stands
        assert stage._recover_overwrite(ws) == "finished"
        assert (ws / "images" / "new.png").is_file() and load_report(ws).success and not old.exists()
        assert not (ws / "sparse").exists()  # (the old one's, dropped; the new run had not made one here)
        return
    # killed while the old files came back: the new run's files already gone, images/ back, the rest still aside
    for name in ("images", "reconstruct_report.json"):
        stage._remove(ws / name)
    old.rename(ws / OVERWRITE_RESTORING)
    (ws / OVERWRITE_RESTORING / "images").rename(ws / "images")
    if moment == "restoring-twice":
        (ws / OVERWRITE_RESTORING / "database.db").rename(ws / "database.db")
    assert stage._recover_overwrite(ws) == "restored"
    assert _files(ws) == before and not (ws / OVERWRITE_RESTORING).exists()
    assert stage._recover_overwrite(ws) is None  # (nothing left: run again, it changes nothing)
    assert _files(ws) == before


def test_masks_drawn_by_hand_that_overwrite_masks_replaces_come_back_on_failure(tmp_path, monkeypatch):
    """--overwrite --masks on a workspace with masks drawn by hand: the new run replaces masks/, so they go aside with
    the rest and come back when it fails (the review found the new masks in their place, "back as it was")."""
    photos = _photos(tmp_path)
    masks = tmp_path / "given_masks"
    masks.mkdir()
    ws = _finished_workspace(tmp_path)
    before = _files(ws)

    def fail(*a, **k):
        (ws / "masks").mkdir(exist_ok=True)
        (ws / "masks" / "a.png.png").write_bytes(b"the new run's")
        raise UserError("mapping failed")

    monkeypatch.setattr(stage.sfm, "stage_inputs", fail)
    with pytest.raises(UserError, match="mapping failed"):
        stage.run(photos, ws, ReconstructConfig(overwrite=True, masks=masks))
    after = _files(ws)
    after.pop(".reconstruct_report.failed.json")
    assert after == before


def test_a_workspace_being_reconstructed_is_named_as_such(tmp_path):
    """train on a workspace whose reconstruction runs now was told it had been stopped, and to run reconstruct."""
    import subprocess
    import sys
    import time

    from uncertsplat.sfm.report import UNFINISHED, require_successful

    ws = tmp_path / "ws"
    write_report(ws, _report(success=False, message=UNFINISHED))
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from uncertsplat.io.atomic import run_lock\n"
        f"with run_lock({str(ws)!r}, 'reconstruct'):\n    print('held', flush=True); time.sleep(30)")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(UserError, match="a reconstruction is writing this workspace now") as err:
            require_successful(ws)
        assert "Wait for it to finish" in err.value.hint
    finally:
        holder.kill()
        holder.wait()
    time.sleep(0.05)
    with pytest.raises(UserError, match="stopped before it finished"):
        require_successful(ws)


def test_photos_in_a_subfolder_are_pointed_out(tmp_path):
    from uncertsplat.sfm.reconstruct import scan_photos

    (tmp_path / "images").mkdir()
    for i in range(3):
        (tmp_path / "images" / f"{i}.jpg").write_bytes(b"not really a jpeg")
    with pytest.raises(UserError, match=r"sub-folder .*images holds photos: pass that folder instead"):
        scan_photos(tmp_path)


def test_photos_two_levels_down_and_in_several_subfolders_are_pointed_out(tmp_path):
    from uncertsplat.sfm.reconstruct import scan_photos

    deep = tmp_path / "capture" / "dcim"
    deep.mkdir(parents=True)
    (deep / "0.jpg").write_bytes(b"x")
    with pytest.raises(UserError, match=r"sub-folder .*capture/dcim holds photos"):
        scan_photos(tmp_path)
    other = tmp_path / "b"
    other.mkdir()
    (other / "1.jpg").write_bytes(b"x")
    with pytest.raises(UserError, match=r"sub-folders .*b, .*capture/dcim hold photos: pass one of them"):
        scan_photos(tmp_path)


# ------------------------------------------------------------------------------------------ mapping runs
def attempt(seed: int, images: int = 49, observations: int = 50_000, focal: float = 820.0, relaxed: bool = False):
    return {"seed": seed, "relaxed": relaxed, "num_images": images, "num_points3d": observations // 3,
            "num_observations": observations, "mean_reprojection_error": 0.4, "focal_lengths": {"1": focal}}


def test_mapping_runs_agree_only_on_the_same_geometry():
    # bonsai's runs (BENCHMARKS.md "Mapping runs that disagree"): right ones agree, one image more or less included
    good = attempt(5, images=49, observations=50_514, focal=800.1)
    assert sfm.attempts_agree(good, attempt(7, images=49, observations=51_570, focal=834.2))
    assert sfm.attempts_agree(good, attempt(6, images=48, observations=50_491, focal=800.1))
    assert not sfm.attempts_agree(good, attempt(0, images=48, observations=25_692, focal=536.6))  # a wrong focal
    assert not sfm.attempts_agree(attempt(0, images=48, observations=25_692, focal=536.6),  # two wrong ones
                                  attempt(1, images=48, observations=27_236, focal=523.6))
    # each criterion on its own, just inside and just outside its tolerance
    lo = 1.0 - sfm.AGREE_OBSERVATIONS
    assert sfm.attempts_agree(attempt(0, observations=100_000), attempt(1, observations=round(100_000 * lo) + 1))
    assert not sfm.attempts_agree(attempt(0, observations=100_000), attempt(1, observations=round(100_000 * lo) - 1))
    lo = 1.0 - sfm.AGREE_FOCAL
    assert sfm.attempts_agree(attempt(0, focal=1000.0), attempt(1, focal=1000.0 * lo + 0.1))
    assert not sfm.attempts_agree(attempt(0, focal=1000.0), attempt(1, focal=1000.0 * lo - 0.1))
    assert sfm.attempts_agree(attempt(0, images=49), attempt(1, images=48))  # at least one image of slack
    assert not sfm.attempts_agree(attempt(0, images=49), attempt(1, images=47))
    assert sfm.attempts_agree(attempt(0, images=1000), attempt(1, images=980))  # 2 % of many
    assert not sfm.attempts_agree(attempt(0, images=1000), attempt(1, images=979))
    # no model, or no observation: nothing to agree on
    empty = {**attempt(2, images=0, observations=0), "focal_lengths": {}}
    assert not sfm.attempts_agree(empty, empty)
    # cameras only one run estimated are not compared; a shared one that differs is
    a = {**attempt(0), "focal_lengths": {"1": 800.0, "2": 600.0}}
    assert sfm.attempts_agree(a, {**attempt(1), "focal_lengths": {"1": 800.0}})
    assert not sfm.attempts_agree(a, {**attempt(1), "focal_lengths": {"1": 800.0, "2": 300.0}})


def test_the_kept_mapping_run_explains_the_most_observations():
    runs = [attempt(0, images=48, observations=21_272), attempt(1, observations=50_518), attempt(2, observations=29_961)]
    assert sfm.choose_attempt(runs, needed=40) == 1
    # runs below the registration bar only count when no run reaches it
    runs = [attempt(0, images=30, observations=90_000), attempt(1, images=45, observations=40_000)]
    assert sfm.choose_attempt(runs, needed=40) == 1
    assert sfm.choose_attempt(runs, needed=46) == 0
    # ties: more images, then the earlier run
    assert sfm.choose_attempt([attempt(0, images=40), attempt(1, images=41)], needed=1) == 1
    assert sfm.choose_attempt([attempt(0), attempt(1)], needed=1) == 0


def test_train_warns_when_the_model_cannot_fit_its_own_photos(tmp_path):
    from uncertsplat.train.session import POOR_FIT_PSNR, poor_fit_warnings

    assert poor_fit_warnings(None, tmp_path) == []
    assert poor_fit_warnings(POOR_FIT_PSNR, tmp_path) == []
    (plain,) = poor_fit_warnings(POOR_FIT_PSNR - 1.1, tmp_path)  # not a reconstruct workspace
    assert "18.90 dB" in plain and "camera poses" in plain and "reconstruct_report" not in plain
    # just below the threshold reads as below it (it printed "20.0 dB (below 20 dB)")
    (edge,) = poor_fit_warnings(POOR_FIT_PSNR - 0.004, tmp_path)
    assert "19.99 dB (below 20 dB)" in edge
    write_report(tmp_path, _report(num_points3d=6084, mean_reprojection_error=1.028, mapping_agreed=False))
    (warning,) = poor_fit_warnings(18.9, tmp_path)
    assert str(tmp_path / REPORT_NAME) in warning and "6,084 points" in warning and "1.03 px" in warning
    assert "disagreed" in warning and "--seed" in warning
    # the workspace a pipeline's reconstruct stage wrote: the advice is that stage's key
    from uncertsplat.stages.manifest import start_manifest, write_manifest

    write_manifest(tmp_path, start_manifest("reconstruct", "sfm", {"seed": 3}, {}))
    (staged,) = poor_fit_warnings(18.9, tmp_path)
    assert "running the pipeline again with --set sfm.seed=4 maps the photos again" in staged
    assert "--overwrite" not in staged
    (tmp_path / "manifest.json").unlink()
    (tmp_path / REPORT_NAME).write_text("{not json")  # a damaged report does not fail a finished training
    (damaged,) = poor_fit_warnings(18.9, tmp_path)
    assert "camera poses" in damaged
    # settings of the fit changed from their defaults come first (a helper's lr.scales of 1e12 was blamed on photos)
    from uncertsplat.config import train_config_from

    (changed,) = poor_fit_warnings(18.9, tmp_path, train_config_from(None, {"lr": {"scales": 1e12},
                                                                            "variational": {"gate_prior_mean": -5.0}}))
    assert "check the settings changed from their defaults (lr.scales, variational.gate_prior_mean), the camera" \
        in changed
    (same,) = poor_fit_warnings(18.9, tmp_path, train_config_from("demo", {}))  # a preset changes none of them
    assert "changed from their defaults" not in same


def test_train_notes_disagreeing_mapping_runs_before_it_starts(tmp_path):
    from uncertsplat.train.session import workspace_notes

    assert workspace_notes(tmp_path) == []  # no report: another kind of scene
    runs = [{"seed": 0, "relaxed": False, "num_images": 3, "num_points3d": 10, "num_observations": 30},
            {"seed": 1, "relaxed": False, "num_images": 3, "num_points3d": 20, "num_observations": 61, "kept": True}]
    write_report(tmp_path, _report(mapping_agreed=True, mapping_attempts=runs))
    assert workspace_notes(tmp_path) == []
    write_report(tmp_path, _report(mapping_agreed=False, mapping_attempts=runs))
    (note,) = workspace_notes(tmp_path)
    assert "disagreed" in note and "kept seed 1, 61 feature observations" in note and "--seed" in note
    (tmp_path / REPORT_NAME).write_text("{not json")
    assert workspace_notes(tmp_path) == []


def test_a_mapping_run_agrees_only_with_runs_of_its_own_options():
    runs = [attempt(0, observations=25_692, focal=536.6), attempt(1, observations=50_514, focal=800.1),
            attempt(2, observations=51_570, focal=834.2, relaxed=True)]
    assert sfm.agreeing(runs[:1], 0) is None  # the only run: nothing to agree with
    assert sfm.agreeing(runs[:2], 1) is False
    assert sfm.agreeing(runs, 2) is None  # the one relaxed run is not compared with the normal ones
    runs.append(attempt(3, observations=51_043, focal=829.1))
    assert sfm.agreeing(runs, 3) is True and sfm.agreeing(runs, 1) is True and sfm.agreeing(runs, 0) is False


@pytest.mark.parametrize("features, guided", [("sift", False), ("dsp-sift", True)])
def test_feature_and_matching_options_reach_colmap(tmp_path, monkeypatch, features, guided):
    """``features`` and ``guided_matching`` set COLMAP's options (the pycolmap calls are stubbed: no real work)."""
    import pycolmap

    seen = {}
    monkeypatch.setattr(pycolmap, "extract_features",
                        lambda *a, extraction_options, **k: seen.setdefault("extraction", extraction_options))
    monkeypatch.setattr(pycolmap, "match_image_pairs",
                        lambda *a, matching_options, **k: seen.setdefault("matching", matching_options))
    monkeypatch.setattr(sfm, "count_verified_pairs", lambda database: 0)
    cfg = ReconstructConfig(features=features, guided_matching=guided, single_camera=False)
    db = tmp_path / "database.db"
    assert sfm.extract_features(db, tmp_path, {(32, 24): ["a.png"]}, cfg) == {}  # the stub extracted nothing
    sfm.match_features(db, [("a.png", "b.png")], cfg, tmp_path / "scratch")
    sift = seen["extraction"].sift
    dsp = features == "dsp-sift"
    assert sift.estimate_affine_shape is dsp and sift.domain_size_pooling is dsp
    assert seen["matching"].guided_matching is guided


def test_a_workspace_from_before_an_option_existed_is_reused_at_its_default():
    options = ReconstructConfig().model_dump(mode="json", exclude={"overwrite"})
    older = {k: v for k, v in options.items() if k not in ("features", "guided_matching")}
    assert stage._same_options(older, ReconstructConfig())
    assert not stage._same_options(older, ReconstructConfig(features="dsp-sift"))
    assert not stage._same_options({**options, "removed_option": 1}, ReconstructConfig())
    assert not stage._same_options({**options, "matcher": "sequential"}, ReconstructConfig())


def test_a_workspace_made_with_other_options_names_them():
    """`reconstruct PHOTOS -o WS --seed 3` on a workspace made with the default seed said "a workspace made with other
    options" without naming one: the options that differ are named with their two values."""
    options = ReconstructConfig().model_dump(mode="json", exclude={"overwrite", "extend"})
    assert stage._option_changes(options, ReconstructConfig(seed=3)) == "seed 0 then, 3 now"
    assert stage._option_changes(options, ReconstructConfig(seed=3, matcher="sequential")) == (
        "matcher auto then, sequential now, seed 0 then, 3 now")
    assert stage._option_changes(options, ReconstructConfig(overwrite=True)) == ""  # (not a workspace's option)
    assert stage._option_changes({**options, "removed_option": 1}, ReconstructConfig()) == ""


def test_weakly_registered_photos_are_named_fewest_first():
    """Photos with fewer than a fifth of the median photo's observations (a stub with what the function reads)."""

    class Image:
        def __init__(self, name, n):
            self.name, self.num_points3D = name, n

    class Rec:
        def __init__(self, counts):
            self.images = [Image(n, c) for n, c in counts.items()]

        def reg_image_ids(self):
            return range(len(self.images))

        def image(self, i):
            return self.images[i]

    counts = {"a.jpg": 753, "b.jpg": 800, "c.jpg": 32, "d.jpg": 760, "e.jpg": 149, "f.jpg": 151, "g.jpg": 900}
    assert sfm.weakly_registered(Rec(counts)) == {"c.jpg": 32, "e.jpg": 149}  # median 753: below 150.6
    assert sfm.weakly_registered(Rec({"a.jpg": 1000, "b.jpg": 1100, "c.jpg": 950})) == {}
    assert sfm.weakly_registered(Rec({"a.jpg": 1000, "b.jpg": 1})) == {}  # two photos: no median to speak of
    # fewer than a fifth: exactly a fifth of the median is not named
    assert sfm.weakly_registered(Rec({"a.jpg": 1000, "b.jpg": 1000, "e.jpg": 1000, "c.jpg": 200, "d.jpg": 199})) == {
        "d.jpg": 199}


def test_a_photo_whose_own_focal_length_stands_apart_is_named(monkeypatch):
    """``focal_outliers`` with pycolmap's pose estimation replaced by what it would find: each photo's own focal
    length (its ratio to the shared camera's is read from its first point's x). Camera 1: five photos within 0.5 %,
    one 25 % longer (a crop saved at full size); the robust spread (1.4826 x the median absolute deviation) keeps the
    threshold at 3 % where the outlier's own spread would lift a standard deviation's 6x to 50 %. A photo with
    fewer than 30 points is not estimated, nor is a camera of two photos."""
    from types import SimpleNamespace

    class Camera:
        def __init__(self, model="PINHOLE", width=100, height=80, params=(100.0, 100.0, 50.0, 40.0)):
            self.model, self.width, self.height, self.params = model, width, height, np.array(params, dtype=float)

        def mean_focal_length(self):
            return float(self.params[:2].mean())

    ratios = {"a": 1.0, "b": 1.005, "c": 0.995, "d": 1.002, "e": 0.998, "crop": 1.25, "few": 2.0, "x": 1.0, "y": 1.6}
    names = list(ratios)

    def image(name, camera_id, points):
        code = float(names.index(name))
        pts = [SimpleNamespace(xy=(code, 0.0), point3D_id=k, has_point3D=lambda: True) for k in range(points)]
        pts.append(SimpleNamespace(xy=(0.0, 0.0), point3D_id=-1, has_point3D=lambda: False))
        return SimpleNamespace(name=f"{name}.jpg", camera_id=camera_id, points2D=pts)

    images = [image(n, 1, 40) for n in "abcde"] + [image("crop", 1, 40), image("few", 1, 29)]
    images += [image("x", 2, 40), image("y", 2, 40)]
    rec = SimpleNamespace(reg_image_ids=lambda: range(len(images)), image=lambda i: images[i],
                          cameras={1: Camera(), 2: Camera()},
                          points3D={k: SimpleNamespace(xyz=(0.0, 0.0, float(k))) for k in range(40)})

    def estimate(xy, xyz, own, estimation, refinement):
        assert estimation.estimate_focal_length and refinement.refine_focal_length and len(xy) == len(xyz) >= 30
        own.params[:2] *= ratios[names[int(xy[0, 0])]]
        return {}

    monkeypatch.setattr(sfm, "pycolmap", SimpleNamespace(
        Camera=Camera, AbsolutePoseEstimationOptions=SimpleNamespace, AbsolutePoseRefinementOptions=SimpleNamespace,
        estimate_and_refine_absolute_pose=estimate))
    got = sfm.focal_outliers(rec)
    middle = float(np.median(np.log([ratios[n] for n in ("a", "b", "c", "d", "e", "crop")])))
    assert list(got) == ["crop.jpg"] and got["crop.jpg"] == pytest.approx(1.25 / np.exp(middle), rel=1e-9)
    ratios["crop"] = 1.028  # within 3 % of the others' median: not named
    assert sfm.focal_outliers(rec) == {}
    ratios.update(b=1.0, c=1.0, d=1.0, e=1.0, crop=1.02)  # no spread at all: still 3 % at least
    assert sfm.focal_outliers(rec) == {}


def test_the_weak_registration_note_suggests_only_options_not_used():
    weak = {"c.jpg": 32}
    note = stage.weak_registration_note(weak, ReconstructConfig())
    assert "c.jpg (32)" in note and "--features dsp-sift --set guided_matching=true" in note
    note = stage.weak_registration_note(weak, ReconstructConfig(features="dsp-sift"))
    assert "--features" not in note and "--set guided_matching=true" in note
    note = stage.weak_registration_note(weak, ReconstructConfig(features="dsp-sift", guided_matching=True))
    assert "--features" not in note and "guided" not in note and "add photos between these" in note


def test_train_notes_training_images_a_downscale_made_tiny():
    """The paper preset's downscale 8 on 400 px photos trains at 50 px: `train` says so with a downscale that
    trains at about 800 px (or the photos' own size); images large enough, or not downscaled, get no note."""
    from uncertsplat.train.session import small_images_notes

    (note,) = small_images_notes(50, 37, 8.0)
    assert "50x37" in note and "about 400 px" in note and "--set scene.downscale=1 " in note
    (note,) = small_images_notes(150, 100, 40.0)  # 6000 px photos at 40: 7.5 -> about 800 px
    assert "--set scene.downscale=7.5 trains at about 800 px" in note
    (note,) = small_images_notes(200, 150, 8.0)  # a phone's photos resized by reconstruct to 1600 px, then 1/8
    assert "200x150" in note and "--set scene.downscale=2 trains at about 800 px" in note
    assert small_images_notes(402, 300, 2.0) == [] and small_images_notes(100, 75, 1.0) == []
    assert small_images_notes(504, 378, 8.0) == []  # the paper's LLFF setting
    assert small_images_notes(394, 295, 2.0) == []  # fern's workspace (787x590) through pipelines/photos.toml


@pytest.mark.parametrize(("seconds", "shown"), [(0.0, "< 0.1 s"), (0.04, "< 0.1 s"), (0.43, "0.4 s"), (9.94, "9.9 s"),
                                                 (12.4, "12 s"), (135.0, "135 s")])
def test_a_mapping_runs_time_is_never_shown_as_zero(seconds, shown):
    """The mapping-runs line said "in 0 s" for a small scene's runs."""
    assert stage._secs(seconds) == shown


def test_an_interrupted_run_is_recognised_and_started_over(tmp_path, monkeypatch):
    """Ctrl-C during the work leaves a report marked unfinished; the same command then starts over in that folder
    instead of refusing it as someone else's files."""
    from uncertsplat.errors import Interrupted

    photos = _photos(tmp_path)
    ws = tmp_path / "ws"

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(stage.sfm, "stage_inputs", stop)
    with pytest.raises(Interrupted, match="interrupted") as err:
        stage.run(photos, ws, ReconstructConfig())
    assert "same command again" in str(err.value)
    left = load_report(ws)
    assert not left.success and left.message.startswith("unfinished")
    (ws / "database.db").write_bytes(b"half written")
    monkeypatch.setattr(stage.sfm, "stage_inputs", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("reached")))
    with pytest.raises(RuntimeError, match="reached"):  # the second run got past the folder check
        stage.run(photos, ws, ReconstructConfig())
    assert not (ws / "database.db").exists()  # the unfinished run's files were cleared first


def test_registration_hints_name_the_causes_this_run_shows_first():
    split = stage.registration_hints([13, 7], "exhaustive", 20, ReconstructConfig())
    assert split[0].startswith("mapping split the photos into 2 groups (13, 7 images")
    assert split[-1] == "or lower --min-registered (now 0.8)"
    small = stage.registration_hints([3], "exhaustive", 20, ReconstructConfig(max_image_size=100))
    assert small[0] == "raise --max-image-size (now 100 px: small images give few features)"
    plain = stage.registration_hints([15], "sequential", 20, ReconstructConfig())
    assert plain[0].startswith("take more photos") and "try --matcher exhaustive" in plain[-2]


def test_photos_of_formats_not_read_and_other_files_are_named(tmp_path):
    from uncertsplat.sfm.reconstruct import scan_photos

    photos = _photos(tmp_path)
    (photos / "IMG_9999.HEIC").write_bytes(b"heic")
    (photos / "DSC_0001.NEF").write_bytes(b"raw")
    (photos / "notes.txt").write_text("shot at noon")
    (photos / ".DS_Store").write_bytes(b"x")
    scan = scan_photos(photos)
    assert len(scan.photos) == 3
    assert ("2 photo(s) in a format this tool does not read left out: DSC_0001.NEF, IMG_9999.HEIC (convert them to "
            "JPEG or PNG to use them)") in scan.notes
    assert "other files ignored: notes.txt" in scan.notes  # hidden files are not worth a line
    (tmp_path / "b").mkdir()
    plain = scan_photos(_photos(tmp_path / "b"))
    assert plain.notes == []


def test_a_run_in_progress_is_not_cleared_by_a_second(tmp_path):
    """The second command finds the folder locked before it looks at (and would clear) the first one's unfinished
    workspace; train names an unfinished workspace as stopped, with the command that finishes it."""
    import fcntl

    from uncertsplat.sfm.report import UNFINISHED, require_successful

    photos = _photos(tmp_path)
    ws = tmp_path / "ws"
    write_report(ws, _report(photos=str(photos.resolve()), success=False, message=UNFINISHED))
    (ws / "database.db").write_bytes(b"being written")
    with open(ws / ".lock", "a+", encoding="utf-8") as held:
        fcntl.flock(held.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(UserError):
            stage.run(photos, ws, ReconstructConfig())
    assert (ws / "database.db").read_bytes() == b"being written" and load_report(ws).message == UNFINISHED
    with pytest.raises(UserError, match="stopped before it finished") as err:
        require_successful(ws)
    assert f"photos {photos.resolve()}, output {ws}, and its options" in " ".join(str(err.value).split())


def test_a_folder_of_photos_in_formats_not_read_says_so(tmp_path):
    from uncertsplat.sfm.reconstruct import scan_photos

    for i in range(3):
        (tmp_path / f"IMG_{i}.HEIC").write_bytes(b"heic")
    with pytest.raises(UserError, match=r"holds no JPEG, PNG or TIFF photos") as err:
        scan_photos(tmp_path)
    assert "3 photo(s) in a format this tool does not read (IMG_0.HEIC, IMG_1.HEIC, IMG_2.HEIC)" in str(err.value)


def test_disagreement_note_names_the_runs_that_agreed_and_why_they_were_not_kept():
    def run(seed, relaxed, images, obs, focal):
        return {"seed": seed, "relaxed": relaxed, "num_images": images, "num_observations": obs,
                "focal_lengths": {"1": focal}}

    # two normal runs agree with each other but register too few images; the relaxed run that registered enough is
    # kept and nothing confirms it
    runs = [run(1, False, 5, 282, 574.0), run(2, False, 5, 283, 575.0), run(1, True, 9, 900, 460.0),
            run(2, True, 9, 500, 900.0)]
    assert sfm.choose_attempt(runs, 7.0) == 2 and sfm.agreeing(runs, 2) is False
    note = stage.disagreement_note(runs, 2, 7.0)
    assert note.startswith("no other mapping run of the same options found the kept run's geometry (seed 1 (relaxed)")
    assert "seed 1 and seed 2 agree with each other but registered 5 images, fewer than needed (7" in note
    assert "focal 460" in note and "seed 2 (relaxed): 9 images, 500 observations, focal 900 px" in note
    # the kept run has the most observations; two others agree on a geometry that explains fewer
    runs = [run(1, False, 9, 900, 460.0), run(2, False, 9, 600, 800.0), run(3, False, 9, 601, 801.0)]
    assert sfm.choose_attempt(runs, 7.0) == 0 and sfm.agreeing(runs, 0) is False
    assert "seed 2 and seed 3 agree with each other but explain fewer feature observations" in \
        stage.disagreement_note(runs, 0, 7.0)
    # none agreeing: no such clause
    assert "agree with each other" not in stage.disagreement_note(runs[:2], 0, 7.0)


def test_photos_larger_than_max_image_size_are_named():
    """A phone's 3200x2400 photos are resized to 1600 px in the workspace: the note says so and what the paper
    preset's 1/8 then trains at; photos that fit get none."""
    note = stage.resized_note({(3200, 2400): ["a.jpg", "b.jpg"], (800, 600): ["c.jpg"]}, 1600)
    assert note.startswith("2 photo(s) larger than max_image_size (1600 px on the longest side; up to 3200x2400)")
    assert "(1600x1200)" in note and "1/8 trains at about 200x150" in note and "--max-image-size N" in note
    assert stage.resized_note({(1600, 1200): ["a.jpg"], (2400, 3200): ["p.jpg"]}, 1600).startswith("1 photo(s)")
    assert stage.resized_note({(1600, 1200): ["a.jpg"]}, 1600) is None


def test_cameras_on_a_line_are_aligned_by_their_rotations():
    """A straight drive: the centres fix no rotation about their line (the comparison reported 94 degrees for
    cameras 0.06 off); the cameras' rotations do. Centres spread out keep Umeyama's fit."""
    rng = np.random.default_rng(5)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rot = q * np.sign(np.linalg.det(q))  # ref_from_model
    n = 40
    src = np.stack([np.linspace(0, 4, n), 1e-4 * rng.normal(size=n), 1e-4 * rng.normal(size=n)], 1)  # on a line
    dst = 2.0 * src @ rot.T + np.array([3.0, 1.0, -2.0]) + 1e-3 * rng.normal(size=(n, 3))  # SfM's noise
    model_rots = [np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(n)]
    model_rots = [r * np.sign(np.linalg.det(r)) for r in model_rots]  # cam_from_model
    ref_rots = [r @ rot.T for r in model_rots]  # cam_from_ref = cam_from_model @ model_from_ref
    s, r, t = sfm.align_cameras(src, dst, model_rots, ref_rots)
    np.testing.assert_allclose(r, rot, atol=1e-9)
    assert s == pytest.approx(2.0, rel=1e-3)
    np.testing.assert_allclose(s * src @ r.T + t, dst, atol=1e-2)
    _, r_centres, _ = sfm.similarity_align(src, dst)
    assert np.abs(r_centres - rot).max() > 0.1  # what the centres alone gave: turned about the line
    spread = rng.normal(size=(n, 3))  # centres spread out: the same as Umeyama's
    got = sfm.align_cameras(spread, 2.0 * spread @ rot.T, model_rots, ref_rots)
    np.testing.assert_allclose(got[1], sfm.similarity_align(spread, 2.0 * spread @ rot.T)[1])


def test_a_weak_registration_far_outside_the_capture_is_left_out():
    """A mirrored copy of a fern photo registered on 13 points 60 units out (every other camera within 5), facing
    away, and was trained on: a ghost scene, the run's frame shrunk 12x. A weakly registered photo more than
    FAR_REGISTRATION median distances out is taken for a wrong pose; a weak one among the others (bonsai's DSCF5763
    on 33 points) and a far one on many points stay."""

    class Image:
        def __init__(self, name, centre, frame_id):
            self.name, self.centre, self.frame_id = name, np.asarray(centre, dtype=float), frame_id

        def projection_center(self):
            return self.centre

    class Rec:
        def __init__(self, centres):
            self.images = {i: Image(n, c, 100 + i) for i, (n, c) in enumerate(centres.items())}
            self.deregistered: list[int] = []

        def reg_image_ids(self):
            return [i for i, im in self.images.items() if im.frame_id not in self.deregistered]

        def image(self, i):
            return self.images[i]

        def deregister_frame(self, frame_id):
            self.deregistered.append(frame_id)

    ring = {f"p{k}.jpg": (np.cos(k), np.sin(k), 0.0) for k in range(8)}
    rec = Rec({**ring, "mirror.jpg": (40.0, 0.0, 60.0), "drone.jpg": (30.0, 0.0, 30.0)})
    far = sfm.far_weak_registrations(rec, {"mirror.jpg": 13, "p3.jpg": 20})
    assert list(far) == ["mirror.jpg"] and far["mirror.jpg"] > sfm.FAR_REGISTRATION  # drone.jpg is not weak
    sfm.leave_out(rec, list(far))
    assert sorted(rec.image(i).name for i in rec.reg_image_ids()) == sorted([*ring, "drone.jpg"])
    assert sfm.far_weak_registrations(Rec(dict(list(ring.items())[:4])), {"p0.jpg": 1}) == {}  # too few to judge
    assert sfm.far_weak_registrations(rec, {}) == {}


def test_feature_extraction_runs_on_as_many_threads_as_memory_holds():
    """20 photos of 4000x3000 with --max-image-size 4000 ended in a segmentation fault in SIFT (2.4 GB a thread,
    every core asked for): the threads are as many as half the free memory holds, said in a note."""
    big = ReconstructConfig(max_image_size=4000, num_threads=16)
    gb = 2**30
    threads, note = sfm.extraction_threads(big, [(4000, 3000), (3000, 4000)], available=8 * gb)
    per = sfm.SIFT_BYTES_PER_PIXEL * 12e6
    assert threads == int(4 * gb // per) == 1 and "instead of 16" in note and "12.0 Mpx" in note
    assert sfm.extraction_threads(big, [(4000, 3000)], available=64 * gb)[0] == int(32 * gb // per) < 16
    # at the default 1600 px the photos are 1.92 Mpx: 16 threads fit in 16 GB, nothing said
    assert sfm.extraction_threads(ReconstructConfig(num_threads=16), [(4000, 3000)], available=16 * gb) == (16, None)
    assert sfm.extraction_threads(big, [(4000, 3000)], available=gb // 100)[0] == 1  # never none
    assert sfm.extraction_threads(big, [], available=gb) == (16, None)


def test_extend_into_a_scene_reconstruct_did_not_make_points_to_a_new_folder(tmp_path):
    """--extend given a synthetic scene (or a COLMAP model made elsewhere) advised `reconstruct PHOTOS -o SCENE`, which
    is refused there and with --overwrite would replace the scene: it says what the folder is and names a new one."""
    photos = _photos(tmp_path)
    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    (scene / "sparse" / "0").mkdir(parents=True)
    with pytest.raises(UserError, match="holds a scene `reconstruct` did not make") as err:
        stage.run(photos, scene, ReconstructConfig(extend=True))
    assert "-o " + str(tmp_path / "scene_ws") in err.value.hint and "--overwrite" not in err.value.hint
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "thesis.docx").write_text("mine")
    with pytest.raises(UserError, match="holds other files"):
        stage.run(photos, tmp_path / "other", ReconstructConfig(extend=True))
    with pytest.raises(UserError, match=r"needs a finished workspace .*\(its report") as err:  # nothing there yet
        stage.run(photos, tmp_path / "nowhere", ReconstructConfig(extend=True))
    assert "Reconstruct the photos first" in err.value.hint


def test_colmap_failing_on_a_full_disk_is_said_as_the_disk(tmp_path, monkeypatch):
    """pycolmap's RuntimeError on a full disk ("No registered database factory succeeded") reached the user as a
    traceback; with the disk nearly full it is said as the disk, and other RuntimeErrors stay what they are."""
    import collections

    photos = _photos(tmp_path)

    def boom(*a, **k):
        raise RuntimeError("No registered database factory succeeded")

    monkeypatch.setattr(stage.sfm, "extract_features", boom)
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(stage.shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 2 * 10**6, 2 * 10**6))
    with pytest.raises(UserError, match=r"No registered database factory succeeded\) with 2 MB left .*the disk is "
                                         "full") as err:
        stage.run(photos, tmp_path / "ws", ReconstructConfig())
    assert "Free some space" in err.value.hint
    monkeypatch.setattr(stage.shutil, "disk_usage", lambda p: usage(10**12, 0, 10**11))
    with pytest.raises(RuntimeError, match="factory"):
        stage.run(photos, tmp_path / "ws2", ReconstructConfig())


def test_extend_without_new_photos_names_those_the_workspace_never_registered(tmp_path):
    """--extend on a folder whose photos the workspace was all made from said it "holds every one of its N photos"
    when some never registered (5 of 24 in a new user's try): the ones found then but not registered are named, with
    why --extend does not try them again."""
    photos = _photos(tmp_path)
    ws = tmp_path / "ws"
    for folder in ("distorted/sparse/0", "sparse/0"):
        (ws / folder).mkdir(parents=True)
    (ws / "database.db").write_bytes(b"")
    _report(photos=str(photos), images_found=["0.png", "1.png", "2.png"],
            images_registered=["0.png"]).write(ws / "reconstruct_report.json")
    with pytest.raises(UserError, match="no new photo") as err:
        stage.run(photos, ws, ReconstructConfig(extend=True))
    message = " ".join(str(err.value).split())
    assert "made from every one of its 3 photos (2 of them not registered then: 1.png, 2.png;" in message
    _report(photos=str(photos), images_found=["0.png", "1.png", "2.png"],
            images_registered=["0.png", "1.png", "2.png"]).write(ws / "reconstruct_report.json")
    with pytest.raises(UserError, match="made from every one of its 3 photos") as err:
        stage.run(photos, ws, ReconstructConfig(extend=True))
    assert "not registered" not in str(err.value)


def test_a_masks_folder_without_a_mask_of_any_photo_is_named_once(tmp_path):
    """`reconstruct PHOTOS --masks FOLDER` with no mask named for a photo: the folder is the error's path, so the
    message says "the folder" rather than its path again ("/x/depth: /x/depth holds no mask ...")."""
    photos = _photos(tmp_path)
    masks = tmp_path / "depth"
    masks.mkdir()
    write_image(masks / "other.png", seed=5)
    with pytest.raises(UserError, match="the folder holds no mask named for any photo") as err:
        stage.run(photos, tmp_path / "ws", ReconstructConfig(masks=masks))
    assert str(err.value).count(str(masks)) == 1 and err.value.path == masks
