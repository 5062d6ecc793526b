"""The report's WebGL viewer (`recon/eval/viewer.js`) against recon's own splat renderer: the
same Gaussians and camera drawn in headless chromium (software WebGL) and by
`recon.gaussians.render` must agree pixel for pixel up to 8-bit rounding. Skipped, with the
reason, where chromium is missing (`make browser`)."""

import base64
import contextlib
import io
import time

import numpy as np
import pytest
import torch
from PIL import Image

from recon.cameras import Cameras
from recon.cameras.look_at import look_at
from recon.eval.viewer import camera_entry, splat_entry, write_page
from recon.gaussians.footprint import with_training_footprint
from recon.gaussians.render import composite_rgbd, project_splats
from recon.metrics.image import psnr
from tests.browser import chromium_driver, console_errors


def random_gaussians(n: int, seed: int = 0) -> dict:
    """`Model.splats()`-shaped Gaussians in a unit box, degree-3 SH."""
    rng = np.random.default_rng(seed)
    return {
        "means": rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32),
        "quats": rng.normal(size=(n, 4)).astype(np.float32),
        "log_scales": np.log(rng.uniform(0.005, 0.08, (n, 3))).astype(np.float32),
        "opacity_logits": rng.normal(0.0, 2.0, n).astype(np.float32),
        "sh": rng.normal(0.0, 0.4, (n, 16, 3)).astype(np.float32),
    }


def view_camera(width: int, height: int) -> Cameras:
    eye = torch.tensor([[1.4, -1.1, 0.7]])
    cam_from_world = look_at(eye, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
    f = 0.9 * width
    K = torch.tensor([[[f, 0.0, width / 2 + 3.0], [0.0, f, height / 2 - 2.0], [0.0, 0.0, 1.0]]])
    return Cameras(K, cam_from_world, torch.tensor([width]), torch.tensor([height]))


def recon_render(g: dict, camera: Cameras, terms: dict) -> np.ndarray:
    """What `GaussianModel.render` draws for these Gaussians: (H, W, 3) in [0, 1]."""
    gaussians = {k: torch.from_numpy(g[k]) for k in ("means", "quats", "log_scales")}
    gaussians["opacity_logits"] = torch.from_numpy(g["opacity_logits"])
    gaussians["sh_dc"] = torch.from_numpy(g["sh"][:, :1])
    gaussians["sh_rest"] = torch.from_numpy(g["sh"][:, 1:])
    with torch.no_grad():
        splats = project_splats(
            gaussians, camera, terms["sh_degree"], terms["near"], terms["antialiased"]
        )
        if terms["intervals"] is not None:
            intervals = torch.from_numpy(terms["intervals"])
            focal = float(camera.K[0, 0, 0])
            splats = with_training_footprint(splats, intervals, focal, terms["antialiased"])
        out = composite_rgbd(splats, torch.tensor(terms["background"]))
    return out["rgb"].clamp(0, 1).numpy()


def one_camera_doc(camera: Cameras, splats: dict, terms: dict) -> dict:
    """A scene of one held-out camera and these Gaussians (`splat_entry`), drawn as `terms`."""
    return {
        "cameras": [camera_entry(camera, "view", "test")],
        "splats": splats,
        "background": terms["background"],
        "near": terms["near"],
        "centre": [0.0, 0.0, 0.0],
        "frustum_size": 0.1,
    }


def wait_until_ready(driver, seconds: float = 20.0) -> None:
    deadline = time.time() + seconds
    while not driver.execute_script("return window.reconViewersReady === true"):
        assert time.time() < deadline, "the viewer never started"
        time.sleep(0.05)


@contextlib.contextmanager
def opened_viewer(folder, doc: dict):
    """Headless chromium (software WebGL) on the page of `doc`, written into `folder`, its
    viewer started."""
    page = write_page(folder, "scene", doc)
    with chromium_driver(webgl=True) as driver:
        driver.get(page.as_uri())
        wait_until_ready(driver)
        yield driver


def browser_render(folder, doc: dict, url: str = "") -> tuple[np.ndarray, dict]:
    """The viewer's image of `doc`'s first camera (cameras and points hidden) -> (H, W, 3) in
    [0, 1] and what the page said (console errors, status line, load time); the page is
    written into `folder` and opened from there, or from `url` (a server of that folder)."""
    page = write_page(folder, "scene", doc)
    with chromium_driver(webgl=True) as driver:
        driver.get(url or page.as_uri())
        wait_until_ready(driver)
        status = driver.execute_script("return document.querySelector('.recon-status').textContent")
        url = driver.execute_script(
            "const v = window.reconViewers.scene; if (!v) return null;"
            "v.showCameras = false; v.showPoints = false; v.setCamera(0, true); return v.snapshot();"
        )
        drawn = driver.execute_script(
            "const v = window.reconViewers.scene; return v && v.count ? v.drawn : null"
        )
        seen = {
            "errors": console_errors(driver),
            "status": status,
            "ready_ms": driver.execute_script("return window.reconViewersReadyMs"),
            "string_intact": driver.execute_script(
                "const s = window.RECON_VIEWS.scene.splats;"
                "return s.bytes === undefined || s.bytes.length === s.bytes_length"
            ),
        }
    assert url is not None, seen
    seen["drawn"] = drawn
    png = base64.b64decode(url.split(",", 1)[1])
    image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), np.float32) / 255
    return image, seen


@pytest.mark.parametrize(
    ("size", "degree", "antialiased", "footprint"),
    [
        ((96, 72), 3, False, False),  # 16 px tiles, every SH band
        ((96, 72), 1, True, True),  # the antialiasing compensation, the footprint filter
        ((480, 400), 2, False, False),  # 32 px tiles (images of 384^2 pixels or more)
    ],
)
def test_the_viewer_draws_what_recon_renders(tmp_path, size, degree, antialiased, footprint):
    g = random_gaussians(400)
    camera = view_camera(*size)
    intervals = None
    if footprint:  # finer than some Gaussians' training views: their dilation grows
        intervals = np.random.default_rng(1).uniform(0.0, 0.02, 400).astype(np.float32)
    terms = {
        "sh_degree": degree,
        "antialiased": antialiased,
        "background": [0.9, 0.8, 0.2],
        "near": 0.01,
        "intervals": intervals,
    }
    doc = one_camera_doc(camera, splat_entry(g, terms), terms)
    expected = recon_render(g, camera, terms)
    seen_image, seen = browser_render(tmp_path / "page", doc)
    assert seen["errors"] == [], seen
    assert seen_image.shape == expected.shape
    value = float(psnr(torch.from_numpy(seen_image), torch.from_numpy(expected)))
    assert value >= 40.0, (value, seen)


def test_splats_the_view_cannot_show_are_left_out_before_the_shader(tmp_path):
    """Gaussians spread far beyond the view (behind the camera, off to every side, some large
    enough to reach in from outside): the viewer hands the shader only those whose 3-sigma
    box can meet the image, and draws what recon renders (nothing it needs was left out)."""
    g = random_gaussians(400, seed=7)
    rng = np.random.default_rng(8)
    g["means"] = rng.uniform(-3.0, 3.0, (400, 3)).astype(np.float32)
    g["log_scales"] = np.log(rng.uniform(0.01, 0.4, (400, 3))).astype(np.float32)
    camera = view_camera(96, 72)
    # 40 round, opaque ones centred 0.5-2 sigma outside the image's edges: their tails are in it
    z, sigma = 1.5, 0.15
    sigma_px = float(camera.K[0, 0, 0]) * sigma / z
    edge = rng.integers(0, 4, 40)
    along, out = rng.uniform(0, 1, 40), rng.uniform(0.5, 2.0, 40) * sigma_px
    u = np.where(edge == 0, -out, np.where(edge == 1, 96 + out, along * 96))
    v = np.where(edge == 2, -out, np.where(edge == 3, 72 + out, along * 72))
    K_inv = torch.linalg.inv(camera.K[0]).numpy()
    cam_points = (K_inv @ np.stack([u, v, np.ones(40)]) * z).T
    world_from_cam = torch.linalg.inv(camera.cam_from_world[0]).numpy()
    g["means"][:40] = cam_points @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
    g["log_scales"][:40] = np.log(sigma)
    g["opacity_logits"][:40] = 3.0
    terms = {"sh_degree": 1, "antialiased": True, "background": [0.5, 0.5, 0.5], "near": 0.01,
             "intervals": None}  # fmt: skip
    doc = one_camera_doc(camera, splat_entry(g, terms), terms)
    expected = recon_render(g, camera, terms)
    seen_image, seen = browser_render(tmp_path / "page", doc)
    assert seen["errors"] == [], seen
    assert seen["drawn"]["gaussians"] == 400 and seen["drawn"]["visible"] < 300, str(seen["drawn"])
    value = float(psnr(torch.from_numpy(seen_image), torch.from_numpy(expected)))
    assert value >= 40.0, (value, seen)


def test_packed_gaussians_are_drawn_as_they_decode(tmp_path):
    """A large run travels packed (`splat_pack`), its bytes a string of the scene script: the
    viewer's decoding (gunzip and unpacking in JS) and `unpack_splats`' (numpy) give the same
    Gaussians, so the same image, from file:// and from a web server alike."""
    import functools
    import http.server
    import threading

    from recon.gaussians.splat_pack import unpack_splats

    g = random_gaussians(700, seed=3)
    camera = view_camera(96, 72)
    terms = {"sh_degree": 3, "antialiased": False, "background": [0.1, 0.2, 0.3], "near": 0.01,
             "intervals": None}  # fmt: skip
    entry = splat_entry(g, terms, exact_max=0)
    assert entry["encoding"] == "pack" and "means" not in entry
    decoded = unpack_splats(entry, entry["bytes"])
    doc = one_camera_doc(camera, entry, terms)
    expected = recon_render(decoded, camera, terms)
    seen_image, seen = browser_render(tmp_path / "page", doc)
    assert seen["errors"] == [] and seen["string_intact"], seen
    value = float(psnr(torch.from_numpy(seen_image), torch.from_numpy(expected)))
    assert value >= 40.0, value

    class Utf8Scripts(http.server.SimpleHTTPRequestHandler):
        """A server that calls every script UTF-8 (as some do): the string arrives garbled,
        and the viewer reads the script's bytes itself."""

        def guess_type(self, path):
            kind = super().guess_type(path)
            return f"{kind}; charset=utf-8" if str(path).endswith(".js") else kind

        def log_message(self, *args):
            pass

    handler = functools.partial(Utf8Scripts, directory=str(tmp_path / "page"))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/index.html"
        served, seen = browser_render(tmp_path / "page", doc, url=url)
    finally:
        server.shutdown()
    assert not seen["string_intact"]  # garbled by the charset: read from the script's bytes
    assert [e for e in seen["errors"] if "favicon.ico" not in e] == [], seen
    assert float(psnr(torch.from_numpy(served), torch.from_numpy(expected))) >= 40.0


def snapshot_image(url: str) -> np.ndarray:
    png = base64.b64decode(url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), np.float32) / 255


def test_a_moving_view_keeps_its_frame_budget_and_rests_in_full(tmp_path):
    """While the view moves, a frame is drawn at the level of detail the last one's time
    allows (`nextLod`'s worked examples: a coarser resolution first, then fewer Gaussians);
    at half resolution it is recon's render at half the size, bilinearly upsampled; at half
    the Gaussians, the most prominent half (opacity x cube root of det Sigma) is drawn; once
    the view rests (SETTLE_MS), the full frame again, pixel for pixel."""
    import torch.nn.functional as F

    from recon.gaussians.projection import covariance_3d

    g = random_gaussians(400, seed=5)
    camera = view_camera(96, 72)
    terms = {"sh_degree": 2, "antialiased": False, "background": [0.2, 0.3, 0.9], "near": 0.01,
             "intervals": None}  # fmt: skip
    doc = one_camera_doc(camera, splat_entry(g, terms), terms)
    viewer = "const v = window.reconViewers.scene;"
    with opened_viewer(tmp_path / "page", doc) as driver:
        examples = driver.execute_script(
            "const L = window.reconLod; return [L.nextLod({scale: 1, share: 1}, 800),"
            " L.nextLod({scale: 0.25, share: 1}, 100), L.nextLod({scale: 0.25, share: 0.5}, 20),"
            " L.nextLod({scale: 0.5, share: 1}, 40), L.lodFor(1600), L.lodFor(10)]"
        )
        full = driver.execute_script(
            viewer + "v.showCameras = false; v.setCamera(0, true); return v.snapshot()"
        )
        half = driver.execute_script(
            viewer
            + "v.lod = {scale: 0.5, share: 1}; v.render(true); return [v.snapshot(), v.drawn]"
        )
        some = driver.execute_script(
            viewer + "v.lod = {scale: 1, share: 0.5}; v.render(true);"
            "return [v.drawn, Array.from(v.order.subarray(0, v.drawn.visible))]"
        )
        time.sleep(0.6)
        rest = driver.execute_script(viewer + "return [v.snapshot(), v.drawn]")
        errors = console_errors(driver)
    assert errors == []
    lods = [(round(e["scale"], 4), round(e["share"], 4)) for e in examples]
    assert lods == [(0.25, 1), (0.25, 0.475), (0.25, 1), (0.5, 1), (0.25, 0.475), (1, 1)]
    # half resolution: recon's render of the camera at 48 x 36, upsampled (half-pixel centres)
    assert (half[1]["width"], half[1]["height"], half[1]["gaussians"]) == (48, 36, 400)
    small = Cameras(camera.K.clone(), camera.cam_from_world, torch.tensor([48]), torch.tensor([36]))
    small.K[:, :2] *= 0.5
    coarse = torch.from_numpy(recon_render(g, small, terms)).permute(2, 0, 1)[None]
    upsampled = F.interpolate(coarse, size=(72, 96), mode="bilinear", align_corners=False)[0]
    seen = torch.from_numpy(snapshot_image(half[0])).permute(2, 0, 1)
    assert float(psnr(seen, upsampled)) >= 40.0
    # half the Gaussians: the most prominent half
    cov = covariance_3d(torch.from_numpy(g["quats"]).double(),
                        torch.from_numpy(g["log_scales"]).double())  # fmt: skip
    opacity = torch.sigmoid(torch.from_numpy(g["opacity_logits"]).double())
    prominence = opacity * torch.linalg.det(cov).clamp(min=0) ** (1 / 3)
    assert some[0]["gaussians"] == 200
    chosen = prominence[torch.tensor(some[1])]  # float32 in the browser: near-ties may swap
    assert len(set(some[1])) == some[0]["visible"] <= 200
    assert float(chosen.min()) >= float(prominence.sort(descending=True).values[199]) * (1 - 1e-5)
    # at rest: the full frame
    assert rest[1]["scale"] == 1 and rest[1]["gaussians"] == 400
    assert np.array_equal(snapshot_image(rest[0]), snapshot_image(full))


def test_a_click_on_a_camera_flies_to_it(tmp_path):
    """Two cameras; from the first, a click where the second's centre is drawn flies to the
    second (and the list follows); a click on empty space does nothing."""
    from selenium.webdriver.common.action_chains import ActionChains

    first = view_camera(96, 72)
    eye = torch.tensor([[-1.0, 1.0, -0.4]])  # beyond the scene, seen by the first camera
    second = Cameras(
        first.K.clone(),
        look_at(eye, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0])),
        first.width.clone(),
        first.height.clone(),
    )
    doc = {
        "cameras": [camera_entry(first, "a", "test"), camera_entry(second, "b", "train")],
        "background": [1.0, 1.0, 1.0],
        "near": 0.01,
        "centre": [0.0, 0.0, 0.0],
        "frustum_size": 0.05,
    }
    # where the first camera sees the second's centre
    p = first.cam_from_world[0] @ torch.cat([eye[0], torch.ones(1)])
    u = float(first.K[0, 0, 0] * p[0] / p[2] + first.K[0, 0, 2])
    v = float(first.K[0, 1, 1] * p[1] / p[2] + first.K[0, 1, 2])
    assert 0 < u < 96 and 0 < v < 72
    page = write_page(tmp_path / "page", "scene", doc)
    with chromium_driver(webgl=True) as driver:
        driver.get(page.as_uri())
        wait_until_ready(driver)
        driver.execute_script("window.reconViewers.scene.setCamera(0, true)")
        picked = driver.execute_script(f"return window.reconViewers.scene.pickCamera({u}, {v})")
        nothing = driver.execute_script("return window.reconViewers.scene.pickCamera(2, 2)")
        canvas = driver.find_element("css selector", "canvas")
        size = canvas.size  # CSS pixels: the canvas is shown at its own size here
        ActionChains(driver).move_to_element_with_offset(
            canvas, round(u * size["width"] / 96 - size["width"] / 2),
            round(v * size["height"] / 72 - size["height"] / 2),
        ).click().perform()  # fmt: skip
        current = driver.execute_script("return window.reconViewers.scene.current")
        listed = driver.execute_script("return document.querySelector('.recon-cameras').value")
        errors = console_errors(driver)
    assert (picked, nothing) == (1, None)
    assert current == 1 and listed == "1" and errors == []


def test_a_page_without_its_scene_says_so(tmp_path):
    page = write_page(tmp_path / "page", "scene", {"cameras": []})
    (tmp_path / "page" / "scene.js").unlink()
    with chromium_driver(webgl=True) as driver:
        driver.get(page.as_uri())
        status = driver.execute_script("return document.querySelector('.recon-status').textContent")
        errors = console_errors(driver)
    assert status.startswith("3D view unavailable: no scene scene")
    assert all("scene.js" in e for e in errors)  # the missing file, nothing else


def test_the_mvs_mesh_is_drawn_where_it_is_and_on_request(tmp_path):
    """`recon mvs`'s mesh: shown at first where there is nothing else to show (a red box at
    the origin, in the middle of a camera that looks at it), hidden and shown again by its
    checkbox; a page without one has no such checkbox."""
    from recon.eval.viewer import b64

    camera = view_camera(96, 72)
    corners = np.array([[x, y, z] for x in (-0.2, 0.2) for y in (-0.2, 0.2) for z in (-0.2, 0.2)])
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])  # fmt: skip
    doc = {
        "cameras": [camera_entry(camera, "view", "test")],
        "mvs_mesh": {
            "xyz": b64(corners, "<f4"),
            "rgb": b64(np.tile([[255, 0, 0]], (8, 1)), "u1"),
            "faces": b64(faces, "<u4"),
        },
        "background": [1.0, 1.0, 1.0],
        "near": 0.01,
        "centre": [0.0, 0.0, 0.0],
        "frustum_size": 0.05,
    }
    p = camera.cam_from_world[0] @ torch.tensor([0.0, 0.0, 0.0, 1.0])  # the box's centre
    u = round(float(camera.K[0, 0, 0] * p[0] / p[2] + camera.K[0, 0, 2]))
    v = round(float(camera.K[0, 1, 1] * p[1] / p[2] + camera.K[0, 1, 2]))

    def centre_pixel(driver) -> list[int]:
        driver.execute_script("const w = window.reconViewers.scene; w.setCamera(0, true);")
        url = driver.execute_script("return window.reconViewers.scene.snapshot()")
        png = base64.b64decode(url.split(",", 1)[1])
        return list(np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))[v, u])

    page = write_page(tmp_path / "page", "scene", doc)
    with chromium_driver(webgl=True) as driver:
        driver.get(page.as_uri())
        wait_until_ready(driver)
        shown = centre_pixel(driver)
        driver.find_element("css selector", ".recon-show-mvs").click()
        hidden = centre_pixel(driver)
        errors = console_errors(driver)
    assert shown[0] > 100 and shown[1] < 60 and shown[2] < 60, shown  # red, shaded
    assert hidden == [255, 255, 255]
    assert errors == []
    without = write_page(tmp_path / "plain", "scene", {**doc, "mvs_mesh": None})
    with chromium_driver(webgl=True) as driver:
        driver.get(without.as_uri())
        wait_until_ready(driver)
        display = driver.execute_script(
            "return getComputedStyle(document.querySelector('.recon-mvs')).display"
        )
    assert display == "none"


def test_a_scene_script_keeps_its_doc_readable_beside_packed_bytes(tmp_path):
    """The doc is the script's second line (ASCII JSON), the packed bytes a third: read back
    without them, with the format a viewer.js checks before reusing a scene."""
    from recon.eval.viewer import SCENE_FORMAT, scene_doc, write_scene_script

    terms = {"sh_degree": 3, "antialiased": False, "background": [0.0, 0.0, 0.0], "near": 0.01,
             "intervals": None}  # fmt: skip
    entry = splat_entry(random_gaussians(300), terms, exact_max=0)
    doc = {"format": SCENE_FORMAT, "cameras": [], "splats": entry}
    script = write_scene_script(tmp_path, "scene", doc)
    back = scene_doc(script)
    assert back["format"] == SCENE_FORMAT and "bytes" not in back["splats"]
    assert back["splats"]["bytes_length"] == len(entry["bytes"])
    assert script.read_bytes().count(b"\n") == 3  # no raw line feed inside the string
    (tmp_path / "broken.js").write_bytes(b"\xff\xfe")
    assert scene_doc(tmp_path / "broken.js") is None


def test_a_mesh_travels_in_the_scene_frame_with_its_colours(tmp_path, monkeypatch):
    """`mesh_entry`: a PLY in original units -> the normalized frame (x_scene = s R x + t),
    its vertex colours (grey without); nothing for a missing mesh or one over MAX_FACES."""
    from types import SimpleNamespace

    import trimesh

    from recon.cameras.similarity import Similarity
    from recon.eval import viewer

    scene = SimpleNamespace(scene_from_world=Similarity(2.0, np.eye(3), np.array([1.0, 0, 0])))
    box = trimesh.creation.box()
    box.export(tmp_path / "grey.ply")
    entry = viewer.mesh_entry(tmp_path / "grey.ply", scene)
    xyz = np.frombuffer(base64.b64decode(entry["xyz"]), "<f4").reshape(-1, 3)
    np.testing.assert_allclose(xyz, 2.0 * box.vertices + [1.0, 0, 0], atol=1e-6)
    faces = np.frombuffer(base64.b64decode(entry["faces"]), "<u4").reshape(-1, 3)
    assert (faces == box.faces).all()
    assert set(base64.b64decode(entry["rgb"])) <= {180, 102}  # grey (trimesh's own, or ours)
    box.visual.vertex_colors = np.tile([[10, 20, 30, 255]], (len(box.vertices), 1))
    box.export(tmp_path / "coloured.ply")
    rgb = np.frombuffer(
        base64.b64decode(viewer.mesh_entry(tmp_path / "coloured.ply", scene)["rgb"]), "u1"
    )
    assert (rgb.reshape(-1, 3) == [10, 20, 30]).all()
    assert viewer.mesh_entry(tmp_path / "missing.ply", scene) is None
    monkeypatch.setattr(viewer, "MAX_FACES", 5)
    assert viewer.mesh_entry(tmp_path / "grey.ply", scene) is None


def test_sfm_points_travel_as_16_bit_fractions_and_are_drawn_where_they_are(tmp_path):
    from types import SimpleNamespace

    from recon.eval.viewer import points_entry

    rng = np.random.default_rng(0)
    xyz = np.concatenate([rng.uniform(-0.05, 0.05, (200, 3)), [[-1.0, -1, -1], [1.0, 1, 1]]])
    rgb = np.tile([[1.0, 0.0, 0.0]], (len(xyz), 1))
    info = SimpleNamespace(points=torch.from_numpy(xyz).float(), point_colors=rgb)
    entry = points_entry(SimpleNamespace(info=info))
    q = np.frombuffer(base64.b64decode(entry["xyz16"]), "<u2").reshape(-1, 3)
    back = np.array(entry["lo"]) + q / 65535 * (np.array(entry["hi"]) - np.array(entry["lo"]))
    assert np.abs(back - xyz.astype(np.float32)).max() <= 2.0 / 65535 + 1e-7
    camera = view_camera(96, 72)
    doc = {
        "cameras": [camera_entry(camera, "view", "test")],
        "points": entry,
        "background": [1.0, 1.0, 1.0],
        "near": 0.01,
        "centre": [0.0, 0.0, 0.0],
        "frustum_size": 0.05,
    }
    p = camera.cam_from_world[0] @ torch.tensor([0.0, 0.0, 0.0, 1.0])
    u = round(float(camera.K[0, 0, 0] * p[0] / p[2] + camera.K[0, 0, 2]))
    v = round(float(camera.K[0, 1, 1] * p[1] / p[2] + camera.K[0, 1, 2]))
    with opened_viewer(tmp_path / "page", doc) as driver:
        url = driver.execute_script(
            "const w = window.reconViewers.scene; w.showCameras = false; w.showPoints = true;"
            "w.setCamera(0, true); return w.snapshot();"
        )
        errors = console_errors(driver)
    image = np.asarray(
        Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGB")
    )
    red = (image[..., 0] > 150) & (image[..., 1] < 100) & (image[..., 2] < 100)
    ys, xs = np.nonzero(red)
    assert errors == [] and len(xs) > 10
    assert abs(np.median(xs) - u) <= 3 and abs(np.median(ys) - v) <= 3
