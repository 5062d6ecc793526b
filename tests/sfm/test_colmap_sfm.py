"""The pycolmap SfM engine: attempt ladder, pair selection, failure reasons, the zlib import
trap, and (slow) real runs on the first fox photos."""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from recon.cameras.conventions import opencv_c2w_from_opengl_c2w
from recon.metrics.pose import pose_errors
from recon.sfm import colmap_steps as steps
from recon.sfm.colmap_diagnose import ImageMatchStats, image_match_stats, unregistered_reason
from recon.sfm.colmap_retry import image_ids, retry_pairs
from recon.sfm.colmap_sfm import (
    SfmConfig,
    SfmError,
    attempt_ladder,
    camera_groups,
    extraction_key,
    low_parallax,
    run_sfm,
    validate_config,
)
from recon.sfm.photos import Photo, PhotoSet, prepare_photos

FOX = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "fox"
FLOWER = FOX.parent / "llff_flower" / "images_4"
SAMPLE_IMAGES = Path(__file__).resolve().parents[2] / "sample_data" / "images"
WALNUT = FOX.parent / "robovision_mvs_walnut" / "undistorted_images" / "2016_10_24__17_43_02"


def test_zlib_before_pycolmap_keeps_png_and_gzip_working(tmp_path):
    """The trap: importing pycolmap before Python's zlib corrupts the heap of every later zlib
    user (measured: `import pycolmap` then `cv2.imwrite(png)` aborts with "free(): invalid
    pointer" in deflateEnd, exit 134; gzip and numba break the same way). `recon/__init__.py`
    imports zlib first; here the subprocess imports zlib, then pycolmap BEFORE recon, and must
    still write and read PNGs and gzip files."""
    script = textwrap.dedent(
        f"""
        import zlib
        import pycolmap
        import gzip
        import cv2
        import numpy as np
        import recon
        img = (np.arange(64 * 64 * 3) % 251).astype(np.uint8).reshape(64, 64, 3)
        for i in range(10):
            path = r"{tmp_path}/t{{}}.png".format(i)
            assert cv2.imwrite(path, img)
            assert (cv2.imread(path) == img).all()
            with gzip.open(r"{tmp_path}/t.gz", "wb") as f:
                f.write(img.tobytes() * 10)
            with gzip.open(r"{tmp_path}/t.gz", "rb") as f:
                assert f.read() == img.tobytes() * 10
        print("ok")
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "ok"


def test_attempt_ladder():
    small = attempt_ladder(SfmConfig(), 40)
    assert [a.matcher for a in small] == ["exhaustive", "exhaustive", "exhaustive"]
    assert [a.guided_matching for a in small] == [False, False, True]
    assert small[1].max_num_features == 16384 and small[1].peak_threshold < small[0].peak_threshold
    assert small[1].always_upsample and not small[0].always_upsample
    assert small[1].abs_pose_min_num_inliers < small[0].abs_pose_min_num_inliers
    # Attempt 3 changes only the matching, so it keeps attempt 2's features.
    assert extraction_key(small[2]) == extraction_key(small[1]) != extraction_key(small[0])
    big = attempt_ladder(SfmConfig(), 41)
    assert [a.matcher for a in big] == ["retrieval", "retrieval", "exhaustive"]
    assert len(attempt_ladder(SfmConfig(try_harder=False), 40)) == 1
    assert attempt_ladder(SfmConfig(matcher="sequential"), 40)[0].matcher == "sequential"


def test_global_adjustments_are_lighter_only_on_many_photos():
    """Under LIGHT_GLOBAL_BA_IMAGES photos: every 30 % of growth with COLMAP's refinements over
    all points; from there on every 50 %, one refinement, redundant points left out."""
    first = attempt_ladder(SfmConfig(), 67)[0]
    small = steps.incremental_options(first, [f"{i}.jpg" for i in range(67)], 0, 1)
    many = steps.incremental_options(first, [f"{i}.jpg" for i in range(150)], 0, 1)
    assert small.ba_global_frames_ratio == small.ba_global_points_ratio == 1.3
    assert small.ba_global_max_refinements == 5  # COLMAP's own
    assert not small.mapper.ba_global_ignore_redundant_points3D
    assert many.ba_global_frames_ratio == many.ba_global_points_ratio == 1.5
    assert many.ba_global_max_refinements == 1
    assert many.mapper.ba_global_ignore_redundant_points3D
    for options in (small, many):  # adjustments stop at Ceres' relative decrease, not COLMAP's 0
        assert options.ba_global_function_tolerance == options.ba_local_function_tolerance == 1e-6


def test_low_parallax_retry_changes_only_the_initial_pair_angle():
    """A capture with no initial pair at COLMAP's 16 degrees (forward-facing) is mapped again
    from the same features and matches with 4 degrees; never lower than that."""
    first = attempt_ladder(SfmConfig(), 34)[0]
    lower = low_parallax(first)
    assert (first.init_min_tri_angle, lower.init_min_tri_angle) == (16.0, 4.0)
    assert extraction_key(lower) == extraction_key(first)
    assert (lower.matcher, lower.guided_matching) == (first.matcher, first.guided_matching)
    assert "low-parallax" in lower.name and low_parallax(lower) is None


def test_retry_pairs():
    names = [f"{i:03d}.jpg" for i in range(8)]
    pairs = retry_pairs(names, ["003.jpg"], all_pairs=False)
    assert sorted(pairs) == sorted(tuple(sorted((n, "003.jpg"))) for n in names if n != "003.jpg")
    assert len(retry_pairs(names, ["003.jpg"], all_pairs=True)) == 28
    many = [f"{i:04d}.jpg" for i in range(400)]  # beyond 300: sequence neighbours only
    near = retry_pairs(many, ["0205.jpg"], all_pairs=True)  # not a keyframe (every 10th)
    assert ("0204.jpg", "0205.jpg") in near and ("0000.jpg", "0205.jpg") not in near
    assert all("0205.jpg" in pair for pair in near) and len(near) < 60


def test_validate_config_rejects_unknown_choices():
    for bad in ({"matcher": "vocab"}, {"mapper": "hierarchical"}, {"camera_model": "FISHEYE9"}):
        with pytest.raises(ValueError):
            validate_config(SfmConfig(**bad))
    validate_config(SfmConfig(camera_model="OPENCV", mapper="global"))


def test_pairs():
    names = [f"img{i}.jpg" for i in range(12)]
    assert len(steps.exhaustive_pairs(names)) == 66
    shuffled = names[::-1]
    pairs = steps.sequential_pairs(shuffled, overlap=3, num_keyframes=3)
    assert len(pairs) == len(set(pairs))
    assert all(steps.natural_key(a) < steps.natural_key(b) for a, b in pairs)  # img2 before img10
    index = {n: i for i, n in enumerate(names)}
    offsets = {index[b] - index[a] for a, b in pairs}
    assert {1, 2, 3, 4} <= offsets  # the window 1..3 and the quadratic steps 2^k, k < 3
    assert ("img1.jpg", "img5.jpg") in pairs  # quadratic: 1 + 2^2
    assert ("img0.jpg", "img8.jpg") in pairs  # keyframes 0, 4, 8 (every 12 // 3) close the loop
    assert ("img1.jpg", "img9.jpg") not in pairs
    assert len(pairs) == 11 + 10 + 9 + 8 + 1  # i + {1, 2, 3, 4} while < 12, plus (0, 8)


def test_unregistered_reasons():
    def reason(keypoints, raw, inliers, verified, other=None):
        return unregistered_reason(ImageMatchStats(keypoints, raw, inliers, verified), 15, other)

    assert reason(3, 0, 0, 0).startswith("no features: 3 SIFT keypoints")
    assert reason(4000, 9, 0, 0).startswith("too few matches: best partner image has 9")
    assert reason(4000, 120, 11, 0).startswith(
        "no verified pair: best partner has 120 matches but only 11"
    )
    assert "separate, smaller model (#2)" in reason(4000, 900, 300, 4, other=2)
    assert "pose estimation failed" in reason(4000, 900, 300, 4)
    assert "not in the feature database" in unregistered_reason(None, 15, None)


def test_camera_groups_split_mixed_sizes():
    def photo(name, w, h):
        return Photo(Path(name), name, w, h, "RGB", "", name)

    photos = PhotoSet(
        (photo("a", 640, 480), photo("b", 480, 640), photo("c", 640, 480)), (), Path(".")
    )
    assert camera_groups(photos, single_camera=True) == [(["a", "c"], 640), (["b"], 640)]
    assert camera_groups(photos, single_camera=False) == [(["a"], 640), (["b"], 640), (["c"], 640)]


def test_blank_photos_raise_one_line_sfm_error(tmp_path):
    src = tmp_path / "blank"
    src.mkdir()
    for i in range(3):
        Image.fromarray(np.full((120, 160), 90 + 40 * i, np.uint8)).save(src / f"b{i}.png")
    with pytest.raises(SfmError) as info:
        run_sfm(src, tmp_path / "work", SfmConfig(num_threads=1))
    message = str(info.value)
    assert message.startswith("0 of 3 images registered: 3 images have no usable features")
    assert "\n" not in message


def fox_subset(tmp_path: Path, count: int) -> Path:
    """The first `count` fox photos at 1/4 size (270x480), enough for SfM in seconds."""
    out = tmp_path / "fox"
    out.mkdir()
    for path in sorted((FOX / "images").glob("*.jpg"))[:count]:
        Image.open(path).resize((270, 480), Image.LANCZOS).save(out / path.name, quality=95)
    return out


def fox_accuracy(reconstruction) -> dict:
    meta = json.loads((FOX / "transforms.json").read_text())
    ref = {Path(f["file_path"]).name: np.asarray(f["transform_matrix"]) for f in meta["frames"]}
    names = sorted(im.name for im in reconstruction.images.values() if im.has_pose)
    est = []
    for name in names:
        world_from_cam = np.eye(4)
        world_from_cam[:3] = (
            reconstruction.find_image_with_name(name).cam_from_world().inverse().matrix()
        )
        est.append(world_from_cam)
    ref_poses = opencv_c2w_from_opengl_c2w(np.stack([ref[n] for n in names]))
    return pose_errors(np.stack(est), ref_poses, remove_common_rotation=True)


@pytest.mark.slow
@pytest.mark.skipif(not FLOWER.exists(), reason="llff_flower not found beside the repo")
def test_a_forward_facing_capture_registers_every_photo(tmp_path):
    """llff_flower's 34 forward-facing photos: no pair of them has COLMAP's 16 degrees of
    parallax (which the defaults' initial pair needs: they register none, after ~17 s of
    mapping), so the matches are mapped with a 4-degree initial pair straight away, and all
    34 register in one attempt."""
    result = run_sfm(FLOWER, tmp_path / "work", SfmConfig(num_threads=2))
    attempts = result.report["attempts"]
    assert len(attempts) == 1 and result.report["images_registered"] == 34
    assert attempts[0]["options"]["init_min_tri_angle"] == 4.0
    assert 0.5 < attempts[0]["max_pair_parallax_deg"] < 16
    assert "parallax" in attempts[0]["name"]


@pytest.mark.slow
@pytest.mark.skipif(not FOX.exists(), reason="fox data not found beside the repo")
def test_fox_subset_with_an_unrelated_photo(tmp_path):
    """12 fox photos (2 of them smaller: mixed sizes) + 1 noise image: the fox photos register
    with accurate poses and one camera per size, the noise image stays out with a
    database-derived reason, and the engine climbs its whole ladder."""
    src = fox_subset(tmp_path, 12)
    for path in sorted(src.iterdir())[-2:]:
        Image.open(path).resize((216, 384), Image.LANCZOS).save(path, quality=95)
    noise = np.random.default_rng(0).integers(0, 256, size=(480, 270, 3), dtype=np.uint8)
    Image.fromarray(noise).save(src / "zz_noise.png")
    calls = []
    result = run_sfm(src, tmp_path / "work", SfmConfig(num_threads=2), lambda *a: calls.append(a))
    report = result.report
    assert report["images_given"] == report["images_usable"] == 13
    assert report["images_registered"] == result.reconstruction.num_reg_images() == 12
    assert [u["name"] for u in report["unregistered"]] == ["zz_noise.png"]
    assert "match" in report["unregistered"][0]["reason"]
    assert [a["registered"] for a in report["attempts"]] == [12, 12, 12]  # all 3 tried, none got 13
    # photos walked around the fox: pairs with far more than the 16 degrees an initial pair needs
    assert report["attempts"][0]["max_pair_parallax_deg"] > 30
    assert [a["options"]["init_min_tri_angle"] for a in report["attempts"]] == [16, 16, 16]
    # The retries touched only the photo left out: new features for it, matched against all 12.
    assert [a["retried_images"] for a in report["attempts"]] == [
        [],
        ["zz_noise.png"],
        ["zz_noise.png"],
    ]
    assert [a["pairs_matched"] for a in report["attempts"]] == [78, 12, 12]
    keypoints = [
        image_match_stats(tmp_path / "work" / f"attempt{k}" / "database.db", 15) for k in (1, 2)
    ]
    # (the lower peak threshold finds more keypoints; white noise has few stable blobs anyway)
    assert keypoints[1]["zz_noise.png"].num_keypoints > keypoints[0]["zz_noise.png"].num_keypoints
    assert keypoints[1]["0001.jpg"].num_keypoints == keypoints[0]["0001.jpg"].num_keypoints
    points = [a["points3d"] for a in report["attempts"]]
    assert report["chosen_attempt"] == 1 + points.index(max(points))  # ties: most 3D points
    assert [(c["model"], c["width"] // 10) for c in report["cameras"]] == [
        ("PINHOLE", 26),
        ("PINHOLE", 21),
    ]
    assert {im.name for im in result.reconstruction.images.values()} == {
        p.name for p in result.images_dir.iterdir()
    }
    assert 0 < report["mean_reprojection_error_px"] < 1.5 and report["mean_track_length"] > 2.5
    phases = {c[0] for c in calls}
    assert {"features", "matching", "mapping", "undistortion", "features (attempt 2)"} <= phases
    errors = fox_accuracy(result.reconstruction)
    # Quarter-size photos: ~4x the full-size errors (0.12 deg, 0.09 %) are expected.
    assert errors["median_rotation_error_deg"] < 1.0
    assert errors["median_center_error_pct"] < 1.0


def test_image_ids_follow_the_names_whatever_the_threads_finish_first(tmp_path):
    """COLMAP's extractor numbers an image when a worker finishes it; recon imports the images
    first, so ids (and with them pair ids and match orientation) follow the names."""
    photos = prepare_photos(SAMPLE_IMAGES, tmp_path / "images")
    options = attempt_ladder(SfmConfig(), len(photos.photos))[0]
    database = tmp_path / "database.db"
    groups = camera_groups(photos, single_camera=True)
    steps.extract_features(database, photos.staging_dir, groups, options, "OPENCV", 2, _quiet)
    ids = image_ids(database)
    assert [ids[n] for n in photos.names] == list(range(1, len(photos.names) + 1))


def _quiet(*_):
    pass


@pytest.mark.slow
@pytest.mark.skipif(not WALNUT.exists(), reason="walnut data not found beside the repo")
def test_a_hard_ring_registers_the_same_photos_in_every_run(tmp_path):
    """The 12-photo walnut ring (few features on a dark background) needs the whole retry
    ladder; with two threads it registered 8 photos in most runs and 2 in others (image ids
    in finishing order, a two-thread mapper). Two runs now agree."""
    src = tmp_path / "photos"
    src.mkdir()
    for path in sorted(WALNUT.glob("*.png")):
        (src / path.name).symlink_to(path)
    poses = []
    for run in range(2):
        model = run_sfm(src, tmp_path / f"work{run}", SfmConfig(num_threads=2)).reconstruction
        poses.append({im.name: im.cam_from_world().matrix() for im in model.images.values()})
    assert poses[0].keys() == poses[1].keys() and len(poses[0]) >= 8
    for name in poses[0]:
        np.testing.assert_allclose(poses[0][name], poses[1][name], atol=1e-5)


@pytest.mark.slow
@pytest.mark.skipif(not FOX.exists(), reason="fox data not found beside the repo")
def test_single_thread_runs_repeat_exactly(tmp_path):
    """With num_threads=1 and a fixed seed two runs give bit-identical poses."""
    src = fox_subset(tmp_path, 8)
    config = SfmConfig(num_threads=1, try_harder=False)
    poses = []
    for run in range(2):
        model = run_sfm(src, tmp_path / f"work{run}", config).reconstruction
        poses.append({im.name: im.cam_from_world().matrix() for im in model.images.values()})
    assert poses[0].keys() == poses[1].keys() and len(poses[0]) == 8
    for name in poses[0]:
        np.testing.assert_array_equal(poses[0][name], poses[1][name])


@pytest.mark.slow
@pytest.mark.skipif(not FOX.exists(), reason="fox data not found beside the repo")
def test_retrieval_matches_a_third_of_the_pairs_and_registers_every_photo(tmp_path):
    """All 67 fox photos (quarter size): over 40 photos the auto matcher retrieves each photo's
    20 most similar ones instead of matching all 2211 pairs; every photo still registers."""
    src = fox_subset(tmp_path, 67)
    result = run_sfm(src, tmp_path / "work", SfmConfig(try_harder=False))
    report = result.report
    assert report["config"]["matcher"] == "auto"
    assert report["attempts"][0]["options"]["matcher"] == "retrieval"
    assert 67 * 20 // 2 <= report["attempts"][0]["pairs_matched"] <= 2211 // 2
    assert report["images_registered"] == 67
    errors = fox_accuracy(result.reconstruction)
    assert errors["median_rotation_error_deg"] < 0.5
    assert errors["median_center_error_pct"] < 1.0


@pytest.mark.slow
@pytest.mark.skipif(not FOX.exists(), reason="fox data not found beside the repo")
def test_global_mapper_on_fox_subset(tmp_path):
    """GLOMAP (rotation averaging + global positioning) registers the same photos, as accurately."""
    src = fox_subset(tmp_path, 8)
    result = run_sfm(src, tmp_path / "work", SfmConfig(mapper="global", try_harder=False))
    assert result.report["images_registered"] == 8
    errors = fox_accuracy(result.reconstruction)
    assert errors["median_rotation_error_deg"] < 0.5
    assert errors["median_center_error_pct"] < 1.0


def synthetic_model(n_images: int, seed: int = 0):
    """A reconstruction whose observations are exact projections through an OPENCV camera with
    its principal point 10 px right of and 6 px below the centre (cx = 330, cy = 246 for
    640 x 480) and k1 = 0.05, but which starts with the principal point at the centre and no
    distortion: n_images cameras on a ring 4 units out, looking at 300 points in a unit ball."""
    import pycolmap

    rng = np.random.default_rng(seed)
    truth = pycolmap.Camera(
        model="OPENCV", width=640, height=480, params=[500, 500, 330, 246, 0.05, 0, 0, 0]
    )
    start = pycolmap.Camera(
        model="OPENCV", width=640, height=480, params=[500, 500, 320, 240, 0, 0, 0, 0]
    )
    start.camera_id = 1
    model = pycolmap.Reconstruction()
    model.add_camera_with_trivial_rig(start)
    points = rng.normal(size=(300, 3))
    points /= np.maximum(1.0, np.linalg.norm(points, axis=1, keepdims=True))
    tracks: list[list] = [[] for _ in points]
    for i in range(n_images):
        angle = 2 * np.pi * i / n_images
        center = np.array([4 * np.cos(angle), 4 * np.sin(angle), 0.5 * (-1) ** i])
        forward = -center / np.linalg.norm(center)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rotation = np.stack([right, down, forward])  # rows: camera axes in the world
        cam_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ center)
        xy = truth.img_from_cam((points @ rotation.T - rotation @ center).astype(np.float64))
        image = pycolmap.Image(name=f"{i}.png", keypoints=xy, camera_id=1, image_id=i + 1)
        model.add_image_with_trivial_frame(image, cam_from_world)
        for j in range(len(points)):
            tracks[j].append(pycolmap.TrackElement(i + 1, j))
    for xyz, track in zip(points, tracks, strict=True):
        model.add_point3D(xyz, pycolmap.Track(track))
    model.update_point_3d_errors()
    return model


def test_refine_intrinsics_recovers_the_principal_point():
    """Exact observations through a camera whose principal point is off the centre (10, 6 px)
    and with radial distortion: the last adjustment finds both and the reprojection error falls
    from pixels to ~0."""
    model = synthetic_model(12)
    refined = steps.refine_intrinsics(model, principal_point=True)
    camera = model.cameras[1]
    assert refined["principal_point_refined"]
    assert refined["reprojection_error_before_px"] > 1.0
    assert refined["reprojection_error_after_px"] < 0.01
    np.testing.assert_allclose(camera.params[2:4], [330, 246], atol=0.1)
    np.testing.assert_allclose(camera.params[4], 0.05, atol=1e-3)


def test_refine_intrinsics_holds_the_principal_point_of_few_images():
    """Below PRINCIPAL_POINT_MIN_IMAGES images the principal point stays where the mapper put it
    (the focal length and distortion still move)."""
    model = synthetic_model(steps.PRINCIPAL_POINT_MIN_IMAGES - 1)
    refined = steps.refine_intrinsics(model, principal_point=True)
    assert not refined["principal_point_refined"]
    np.testing.assert_array_equal(model.cameras[1].params[2:4], [320, 240])
    assert refined["reprojection_error_after_px"] < refined["reprojection_error_before_px"]
