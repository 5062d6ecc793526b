"""The report's WebGL viewer (`recon/eval/viewer.js`) against recon's own splat renderer: the
same Gaussians and camera drawn in headless chromium (software WebGL) and by
`recon.gaussians.render` must agree pixel for pixel up to 8-bit rounding. Skipped, with the
reason, where chromium is missing (`make browser`)."""

import base64
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


def wait_until_ready(driver, seconds: float = 20.0) -> None:
    deadline = time.time() + seconds
    while not driver.execute_script("return window.reconViewersReady === true"):
        assert time.time() < deadline, "the viewer never started"
        time.sleep(0.05)


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
    doc = {
        "cameras": [camera_entry(camera, "view", "test")],
        "splats": splat_entry(g, terms),
        "background": terms["background"],
        "near": terms["near"],
        "centre": [0.0, 0.0, 0.0],
        "frustum_size": 0.1,
    }
    expected = recon_render(g, camera, terms)
    seen_image, seen = browser_render(tmp_path / "page", doc)
    assert seen["errors"] == [], seen
    assert seen_image.shape == expected.shape
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
    doc = {
        "cameras": [camera_entry(camera, "view", "test")],
        "splats": entry,
        "background": terms["background"],
        "near": 0.01,
        "centre": [0.0, 0.0, 0.0],
        "frustum_size": 0.1,
    }
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
    page = write_page(tmp_path / "page", "scene", doc)
    with chromium_driver(webgl=True) as driver:
        driver.get(page.as_uri())
        wait_until_ready(driver)
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
