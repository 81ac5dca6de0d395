"""Detection with OpenCV's detectors, on real images (tests/data, with their licences) and on
synthetic images with known point positions. Pixels in OpenCV's convention (centre of the
top-left pixel is (0, 0), x right, y down)."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from zoomcalib.detect import (
    Detection,
    detect_folder,
    detect_image,
    detection_pool,
    read_detections,
    write_detections,
)
from zoomcalib.targets import parse_pattern

DATA = Path(__file__).parent / "data"
LEFT = DATA / "opencv-samples"
CHARUCO = DATA / "opencv-charuco"
CHESS = parse_pattern("chessboard:9x6:25")
CHARUCO_SPEC = "charuco:5x7:40:20:DICT_6X6_250"

# OpenCV's unit test test_calibration.py on the left*.jpg set (see tests/data/opencv-samples).
LEFT_K = np.array([[532.8099, 0.0, 342.4952], [0.0, 532.9335, 233.8879], [0.0, 0.0, 1.0]])
LEFT_DIST = np.array([-0.2813256, 0.0291130, 0.0012123, -0.00014083, 0.1548658])


def rms(a: np.ndarray, b: np.ndarray) -> float:
    """RMS distance between two (K, 2) point sets, pixels."""
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def homography_residual(object_xy: np.ndarray, points: np.ndarray) -> float:
    """RMS residual, pixels, of the least-squares homography from object_xy (K, 2) to points."""
    h, _ = cv2.findHomography(object_xy, points, 0)
    fitted = cv2.perspectiveTransform(object_xy[None].astype(np.float64), h)[0]
    return rms(fitted, points)


# ----------------------------------------------------------------------------------------------
# real chessboards


@pytest.fixture(scope="module")
def left_detections():
    return {f: {m: detect_image(LEFT / f, CHESS, m) for m in ("sb", "classic")}
            for f in ("left01.jpg", "left02.jpg", "left12.jpg")}


@pytest.mark.parametrize("name", ["left01.jpg", "left02.jpg", "left12.jpg"])
def test_chessboard_real_sb_and_classic_agree_and_are_ordered(left_detections, name):
    dets = left_detections[name]
    for method, d in dets.items():
        assert d.error is None, d.error
        assert d.ok and d.method == method and d.file == name
        assert d.points.shape == (54, 2) and d.image_size == (640, 480)
        np.testing.assert_array_equal(d.ids, np.arange(54))
        # Order matches the object points: with the lens distortion removed (reference
        # intrinsics), one homography maps the board onto the corners. A wrong row length or a
        # transposed grid gives tens of pixels.
        und = cv2.undistortPoints(d.points[:, None], LEFT_K, LEFT_DIST, P=LEFT_K)[:, 0]
        assert homography_residual(CHESS.object_points[:, :2], und) < 0.5
    # OpenCV's two detectors return this board from opposite ends; normalised, they agree.
    assert rms(dets["sb"].points, dets["classic"].points) < 0.5


@pytest.mark.parametrize("name", ["left01.jpg", "left02.jpg", "left12.jpg"])
def test_chessboard_real_order_follows_the_square_colours(left_detections, name):
    # The 180-degree ambiguity of a 9x6 board is settled by colour: the inner squares with
    # (c + r) even -- the one between corners 0, 1, 9, 10 among them -- are dark.
    grey = cv2.imread(str(LEFT / name), cv2.IMREAD_GRAYSCALE).astype(float)
    g = left_detections[name]["sb"].points.reshape(6, 9, 2)
    centres = 0.25 * (g[:-1, :-1] + g[:-1, 1:] + g[1:, :-1] + g[1:, 1:])
    values = grey[np.rint(centres[..., 1]).astype(int), np.rint(centres[..., 0]).astype(int)]
    rr, cc = np.indices(values.shape)
    even = (rr + cc) % 2 == 0
    assert values[even].max() < values[~even].min()


def test_chessboard_real_depth_and_colour_inputs(rng):
    grey = cv2.imread(str(LEFT / "left01.jpg"), cv2.IMREAD_GRAYSCALE)
    ref = {m: detect_image(grey, CHESS, m) for m in ("sb", "classic")}
    assert ref["sb"].file == "<array>" and ref["sb"].ok
    colour = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    np.testing.assert_array_equal(detect_image(colour, CHESS, "sb").points, ref["sb"].points)
    # 16-bit: the same picture with sub-8-bit noise; classic refines on the 16-bit data.
    wide = np.clip(grey.astype(np.int64) * 256 + rng.integers(0, 256, grey.shape), 0, 65535)
    wide = wide.astype(np.uint16)
    for m in ("sb", "classic"):
        d = detect_image(wide, CHESS, m)
        assert d.ok, d.error
        assert rms(d.points, ref[m].points) < 0.05


# ----------------------------------------------------------------------------------------------
# synthetic chessboards: the colour rule gives the true order at any rotation


def random_homography(target, rng, size, angle, fill=0.75, tilt=0.35):
    """Board (mm) -> image (px) homography: board centred, turned by ``angle``, random tilt."""
    w, h = size
    ext = target.extent_mm
    centre = 0.5 * (ext[:2] + ext[2:])
    scale = fill * min(w, h) / np.hypot(*(ext[2:] - ext[:2]))
    c, s = np.cos(angle), np.sin(angle)
    affine = np.eye(3)
    affine[:2, :2] = scale * np.array([[c, -s], [s, c]])
    affine[:2, 2] = np.array([w / 2, h / 2]) - affine[:2, :2] @ centre
    persp = np.eye(3)
    persp[2, :2] = rng.uniform(-tilt, tilt, 2) / max(w, h)
    shift = np.array([[1.0, 0, -w / 2], [0, 1, -h / 2], [0, 0, 1]])
    return np.linalg.inv(shift) @ persp @ shift @ affine


def render_chessboard(target, hom, size, supersample=4):
    """Dark polygons on white, area-sampled; returns (h, w) uint8 and the true corners (K, 2)."""
    w, h = size
    s = supersample
    big = np.full((h * s, w * s), 255, np.uint8)
    # pixel centres: x_big = s * x + (s - 1) / 2
    to_big = np.array([[s, 0, (s - 1) / 2], [0, s, (s - 1) / 2], [0, 0, 1.0]]) @ hom
    polys = [np.rint(cv2.perspectiveTransform(p[None].astype(np.float64), to_big)[0] * 16)
             .astype(np.int32) for p in target.polygons]
    cv2.fillPoly(big, polys, 0, cv2.LINE_8, 4)
    img = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)
    truth = cv2.perspectiveTransform(target.object_points[None, :, :2], hom)[0]
    return img, truth


@pytest.mark.parametrize("method", ["sb", "classic"])
def test_chessboard_synthetic_order_at_any_rotation(method):
    rng = np.random.default_rng(20240611)
    for spec in ("chessboard:9x6:25", "chessboard:8x6:25"):
        target = parse_pattern(spec)
        for angle in np.deg2rad([0.0, 90.0, 180.0, 270.0]) + rng.uniform(-0.3, 0.3, 4):
            img, truth = render_chessboard(target, random_homography(target, rng, (640, 480),
                                                                     angle), (640, 480))
            d = detect_image(img, target, method)
            assert d.ok, d.error
            if spec.startswith("chessboard:9x6"):
                expected = truth  # colours tell the ends apart: the true order
            else:  # 8x6 looks the same turned by 180 degrees: first point nearest top-left
                expected = min(truth, truth[::-1], key=lambda q: (q[0].sum(), q[0, 1]))
            assert np.abs(d.points - expected).max() < 1.0, (spec, np.rad2deg(angle))


# ----------------------------------------------------------------------------------------------
# ChArUco


def test_charuco_tutorial_photo_full_and_partial():
    target = parse_pattern(CHARUCO_SPEC)
    img = cv2.imread(str(CHARUCO / "img_00.jpg"))
    d = detect_image(CHARUCO / "img_00.jpg", target)
    assert d.ok and d.method == "charuco", d.error
    assert len(d.points) >= 20
    assert np.all((d.ids >= 0) & (d.ids < target.n_points))
    assert len(np.unique(d.ids)) == len(d.ids)
    assert homography_residual(target.object_points[d.ids, :2], d.points) < 0.5
    # A partial view (left half of the photo): only the corners seen, same ids, same places.
    half = detect_image(img[:, :320], target)
    assert half.ok, half.error
    assert 0 < len(half.ids) < len(d.ids)
    assert set(half.ids) <= set(d.ids)
    assert np.all(half.points[:, 0] < 320)
    full_at = {int(i): p for i, p in zip(d.ids, d.points, strict=True)}
    same = np.array([full_at[int(i)] for i in half.ids])
    assert np.abs(half.points - same).max() < 0.5


# ----------------------------------------------------------------------------------------------
# circle grids, synthetic


def render_dots(target, hom, size, shift=8):
    """Filled anti-aliased circles (radius from the local scale) at the projected centres."""
    w, h = size
    centres = cv2.perspectiveTransform(target.object_points[None, :, :2], hom)[0]
    edge = cv2.perspectiveTransform(
        (target.object_points[:, :2] + [target.discs[0, 2], 0.0])[None], hom)[0]
    radii = np.linalg.norm(edge - centres, axis=1)
    img = np.full((h, w), 255, np.uint8)
    for (x, y), r in zip(centres * 2**shift, radii * 2**shift, strict=True):
        cv2.circle(img, (int(round(x)), int(round(y))), int(round(r)), 0, -1, cv2.LINE_AA, shift)
    return img, centres, radii


@pytest.mark.parametrize("spec", ["acircles:4x11:20", "circles:7x5:20"])
def test_circle_grids_synthetic_order_and_accuracy(spec):
    target = parse_pattern(spec)
    rng = np.random.default_rng(7 if spec.startswith("a") else 11)
    smallest = np.inf
    for size in [(800, 600)] * 4 + [(320, 240)]:  # the last: dots about 8 px across
        hom = random_homography(target, rng, size, rng.uniform(-np.pi, np.pi), fill=0.8)
        img, centres, radii = render_dots(target, hom, size)
        smallest = min(smallest, 2 * radii.min())
        d = detect_image(img, target)
        assert d.ok and d.method == "circles", d.error
        np.testing.assert_array_equal(d.ids, np.arange(target.n_points))
        if target.kind == "acircles":
            expected = centres  # no symmetry: the true order
        else:  # the grid looks the same turned by 180 degrees: first point nearest top-left
            expected = min(centres, centres[::-1], key=lambda q: (q[0].sum(), q[0, 1]))
        assert np.linalg.norm(d.points - expected, axis=1).max() < 0.2
    assert smallest < 9.0  # the small-dot case was really exercised


# ----------------------------------------------------------------------------------------------
# folders, errors, files


@pytest.fixture(scope="module")
def mixed_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("mixed")
    rng = np.random.default_rng(5)
    (folder / "corrupt.png").write_bytes(rng.integers(0, 256, 4000, dtype=np.uint8).tobytes())
    cv2.imwrite(str(folder / "blank.PNG"), np.full((480, 640), 200, np.uint8))
    shutil.copy(LEFT / "left01.jpg", folder / "left01.jpg")
    (folder / "notes.txt").write_text("not an image\n")
    return folder


def test_folder_with_bad_images_keeps_going(mixed_folder):
    calls = []
    dets = detect_folder(mixed_folder, CHESS, progress=calls.append)
    assert [d.file for d in dets] == ["blank.PNG", "corrupt.png", "left01.jpg"]
    assert calls == [1, 1, 1]
    blank, corrupt, good = dets
    for bad in (blank, corrupt):
        assert not bad.ok and bad.points.shape == (0, 2) and bad.ids.shape == (0,)
        assert bad.error.startswith(bad.file + ": ") and "\n" not in bad.error
    assert "no chessboard 9x6 found" in blank.error
    assert "cannot read image" in corrupt.error
    assert good.error is None and good.points.shape == (54, 2)


def test_folder_with_workers_gives_the_same_results(mixed_folder):
    serial = detect_folder(mixed_folder, CHESS, "classic")
    calls = []
    parallel = detect_folder(sorted(mixed_folder.iterdir()), CHESS, "classic", workers=2,
                             progress=calls.append)
    # the explicit list is taken as given, notes.txt included (it fails, the others do not)
    assert [d.file for d in parallel] == ["blank.PNG", "corrupt.png", "left01.jpg", "notes.txt"]
    assert len(calls) == 4
    for a, b in zip(serial, parallel[:3], strict=True):
        assert a.error == b.error
        np.testing.assert_array_equal(a.points, b.points)
    assert "cannot read image" in parallel[3].error


def test_a_shared_pool_serves_several_folders_and_is_left_running(mixed_folder):
    # calibrate's steps share one pool of workers: each call gives what its own pool would,
    # and the pool stays usable for the next call until its owner shuts it down
    own = detect_folder(mixed_folder, CHESS, "classic", workers=2)
    pool = detection_pool(2)
    try:
        first = detect_folder(mixed_folder, CHESS, "classic", workers=2, pool=pool)
        second = detect_folder(mixed_folder, CHESS, "classic", workers=2, pool=pool)
        assert pool.submit(int, "7").result() == 7  # still running
    finally:
        pool.shutdown()
    for run in (first, second):
        assert [d.file for d in run] == [d.file for d in own]
        for a, b in zip(own, run, strict=True):
            assert a.error == b.error
            if a.points is not None:
                np.testing.assert_array_equal(a.points, b.points)


def test_bad_inputs_give_one_line_errors(tmp_path):
    missing = detect_image(tmp_path / "nothing.png", CHESS)
    assert missing.error.startswith("nothing.png: cannot read image")
    (tmp_path / "empty.jpg").write_bytes(b"")
    assert detect_image(tmp_path / "empty.jpg", CHESS).error == \
        "empty.jpg: cannot read image (empty file)"
    odd = detect_image(np.zeros((4, 4, 2), np.uint8), CHESS, name="odd")
    assert odd.error.startswith("odd: cannot use image")


def test_unsuitable_method_raises_a_clear_error(mixed_folder):
    with pytest.raises(ValueError, match="'circles' does not fit a chessboard target"):
        detect_image(LEFT / "left01.jpg", CHESS, "circles")
    with pytest.raises(ValueError, match="does not fit a charuco target"):
        detect_folder(mixed_folder, CHARUCO_SPEC, "sb")
    with pytest.raises(ValueError, match="unknown detection method 'harris'"):
        detect_image(LEFT / "left01.jpg", CHESS, "harris")


def test_detections_json_round_trip(mixed_folder, tmp_path):
    dets = detect_folder(mixed_folder, CHESS)
    path = write_detections(tmp_path / "det.json", dets, CHESS)
    raw = json.loads(path.read_text())
    assert raw["pattern"] == "chessboard:9x6:25"
    assert [e["file"] for e in raw["images"]] == ["blank.PNG", "corrupt.png", "left01.jpg"]
    good = raw["images"][2]
    assert {"file", "points", "ids", "error"} <= set(good) and good["error"] is None
    assert len(good["points"]) == 54 and len(good["points"][0]) == 2
    assert good["ids"] == list(range(54))
    assert dets[2].to_dict() == {k: good[k] for k in ("file", "points", "ids", "error")}
    spec, back = read_detections(path)
    assert spec == CHESS.spec and len(back) == len(dets)
    for a, b in zip(dets, back, strict=True):
        assert isinstance(b, Detection)
        assert (a.file, a.error, a.method, a.image_size) == (b.file, b.error, b.method,
                                                             b.image_size)
        np.testing.assert_array_equal(a.points, b.points)  # exact: JSON keeps every digit
        np.testing.assert_array_equal(a.ids, b.ids)
    (tmp_path / "bad.json").write_text('{"images": 3}')
    with pytest.raises(ValueError, match="bad.json: not a detections file"):
        read_detections(tmp_path / "bad.json")


def test_unknown_option_and_missing_folder_raise(tmp_path):
    with pytest.raises(TypeError, match="method 'sb' has no option 'win'"):
        detect_image(LEFT / "left01.jpg", CHESS, "sb", win=3)
    with pytest.raises(FileNotFoundError, match="no such folder"):
        detect_folder(tmp_path / "absent", CHESS)


def test_a_sharpening_camera_is_said_and_its_corners_kept():
    # OpenCV's sample photos as they are, and unsharp-masked as a camera's sharpening does
    # (I + 2 (I - G_2 * I)): only the sharpened ones are fitted as steep edges, the flag goes
    # through the detections file, and no corner is lost to it.
    for path in sorted(LEFT.glob("left0[1-4].jpg")):
        grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        plain = detect_image(grey, "chessboard:9x6:25")
        blurred = cv2.GaussianBlur(grey.astype(float), (0, 0), 2.0)
        sharp = np.clip(grey + 2.0 * (grey - blurred), 0, 255).astype(np.uint8)
        with warnings.catch_warnings():  # no numpy warning leaks from the fits
            warnings.simplefilter("error", RuntimeWarning)
            sharpened = detect_image(sharp, "chessboard:9x6:25", name=path.name)
        assert plain.ok and not plain.steep_edges
        assert sharpened.ok and sharpened.steep_edges and sharpened.n_fallback == 0
        back = Detection.from_dict(json.loads(json.dumps(sharpened.to_dict())))
        assert back.steep_edges and "steep_edges" not in plain.to_dict()


def test_the_fitted_sharpening_goes_through_the_detections_file():
    det = Detection("a.png", np.zeros((2, 2)), [0, 1], sharpening=(0.8, 0.9, 1.2))
    back = Detection.from_dict(json.loads(json.dumps(det.to_dict())))
    assert back.sharpening == (0.8, 0.9, 1.2)
    assert "sharpening" not in Detection("b.png", np.zeros((2, 2)), [0, 1]).to_dict()


def test_a_damaged_png_is_named_without_libpng_printing(tmp_path, capfd):
    # a frame cut short (a copy interrupted) and one with a flipped byte: each is an image
    # error naming the file and the damage, and libpng prints nothing of its own
    grey = cv2.imread(str(LEFT / "left01.jpg"), cv2.IMREAD_GRAYSCALE)
    whole = cv2.imencode(".png", grey)[1].tobytes()
    (tmp_path / "cut.png").write_bytes(whole[:len(whole) // 2])
    flipped = bytearray(whole)
    flipped[len(whole) // 2] ^= 0xFF
    (tmp_path / "flipped.png").write_bytes(bytes(flipped))
    cut = detect_image(tmp_path / "cut.png", "chessboard:9x6:25")
    bad = detect_image(tmp_path / "flipped.png", "chessboard:9x6:25")
    assert cut.error == "cut.png: cannot read image (truncated PNG: chunk IDAT runs past the " \
                        "end of the file)"
    assert bad.error == "flipped.png: cannot read image (corrupt PNG: CRC error in chunk IDAT)"
    assert "libpng" not in capfd.readouterr().err
    (tmp_path / "whole.png").write_bytes(whole)
    assert detect_image(tmp_path / "whole.png", "chessboard:9x6:25").ok
