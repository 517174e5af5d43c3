"""The viser viewer in headless Chromium: it connects, draws the scene, and the frame slider and layer toggles moved
in the page reach the server and change what is drawn. Also the live path (ViserRecorder) and replay (load_rrd)."""

from __future__ import annotations

import shutil
import socket
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from app_fakes import drive, pose

from plvo_app.recording_levels import DetailOptions
from plvo_app.rerun_recorder import RerunOptions, RerunRecorder
from plvo_app.viser_viewer import LAYER_COLORS, LAYERS, SceneStore, ViserRecorder, ViserViewer, _css, load_rrd

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]
N = 9


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(cond, timeout: float = 20.0) -> bool:
    t0 = time.time()
    while time.time() - t0 < timeout:
        if cond():
            return True
        time.sleep(0.1)
    return False


@pytest.fixture(scope="module")
def browser():
    playwright = pytest.importorskip("playwright.sync_api")
    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} not installed (scripts/setup.sh --test installs it)")
    profile = tempfile.mkdtemp(prefix="plvo-chromium-")
    with playwright.sync_playwright() as p:
        ctx = p.chromium.launch_persistent_context(profile, executable_path=CHROMIUM, headless=True, args=ARGS,
                                                   viewport={"width": 1280, "height": 720})
        yield ctx
        ctx.close()
    shutil.rmtree(profile, ignore_errors=True)


@pytest.fixture(scope="module")
def replay_viewer(tmp_path_factory):
    path = tmp_path_factory.mktemp("view") / "fake.rrd"
    rec = RerunRecorder(path)
    drive(rec, N)
    rec.close()
    viewer = ViserViewer(load_rrd(path), port=_free_port())
    yield viewer
    viewer.close()


def _until(grab, cond, timeout: float = 15.0):
    """grab() until cond(result) holds or the timeout passes; returns the last result (the caller asserts)."""
    t0 = time.time()
    while True:
        out = grab()
        if cond(out) or time.time() - t0 > timeout:
            return out
        time.sleep(0.2)


def _n_colours(img: np.ndarray) -> int:
    return len(np.unique(img.reshape(-1, 3), axis=0))


def _changed(a: np.ndarray, b: np.ndarray) -> float:
    return float((np.abs(a.astype(int) - b.astype(int)).max(axis=2) > 30).mean())


def _scene_pixels(page, path: Path) -> np.ndarray:
    import cv2

    page.screenshot(path=str(path))
    img = cv2.imread(str(path))
    return img[150:700, 0:900]  # the 3D canvas, clear of the control panel and the WebGL notice


def test_page_connects_draws_and_follows_slider_toggles_and_play(browser, replay_viewer, tmp_path):
    v = replay_viewer
    page = browser.new_page()
    page.goto(f"http://127.0.0.1:{v.port}")
    page.wait_for_selector("canvas", timeout=30000)
    assert _wait(lambda: len(v.server.get_clients()) == 1)
    page.get_by_text("Connected").wait_for(timeout=20000)
    # the scene arrives and renders asynchronously: poll the canvas rather than sleeping a fixed time
    first = _until(lambda: _scene_pixels(page, tmp_path / "first.png"),
                   lambda img: np.any(img < 235, axis=2).mean() > 0.02 and _n_colours(img) > 50)
    drawn = np.any(first < 235, axis=2).mean()  # the background is white
    assert drawn > 0.02, f"scene looks blank: {drawn:.3%} of the canvas drawn"
    assert _n_colours(first) > 50  # colours of scan, map, image, not a flat fill

    slider = page.get_by_role("slider").first
    assert slider.get_attribute("aria-valuenow") == "0" and v.shown_frame == 0
    slider.focus()
    for _ in range(6):
        page.keyboard.press("ArrowRight")
    assert _wait(lambda: v.slider.value == 6 and v.shown_frame == 6), (v.slider.value, v.shown_frame)
    np.testing.assert_allclose(v._handles["camera"].position, pose(6)[:3, 3], atol=1e-4)
    page.get_by_text("frame 6 (7/9)").wait_for(timeout=10000)
    moved = _until(lambda: _scene_pixels(page, tmp_path / "moved.png"), lambda img: _changed(img, first) > 0.005)
    assert _changed(moved, first) > 0.005

    handles = dict(v._handles)
    page.get_by_role("checkbox", name="scan").uncheck()
    assert _wait(lambda: not v.toggles["scan"].value and not v._handles["scan"].visible)
    # a toggle hides one node; the others are the same nodes, not removed and re-sent
    assert all(v._handles[k] is h for k, h in handles.items())

    page.get_by_role("button", name="Play").click()
    assert _wait(lambda: v.playing and v.shown_frame != 6, timeout=10), "play did not move the frame"
    page.get_by_role("button", name="Pause").click()
    assert _wait(lambda: not v.playing)
    page.close()


@pytest.fixture(scope="module")
def detail_viewer(tmp_path_factory):
    """A default-level replay of 30 fake frames, full detail on 1 in 4 keyframes and around the events."""
    path = tmp_path_factory.mktemp("detail") / "default.rrd"
    rec = RerunRecorder(path, RerunOptions(detail=DetailOptions(keyframe_stride=4)))
    drive(rec, 30)
    rec.close()
    viewer = ViserViewer(load_rrd(path), port=_free_port())
    yield viewer
    viewer.close()


_PANEL_IMAGES = """() => [...document.querySelectorAll('img')].filter(i => i.src.startsWith('blob:')).map(i => {
    const r = i.getBoundingClientRect();
    return [i.naturalWidth, i.naturalHeight, r.x, r.y, r.width, r.height];
})"""


def test_page_shows_the_camera_image_the_legend_and_the_detail_frames(browser, detail_viewer, tmp_path):
    """The sidebar has the camera image (the frame's own on detail frames, else its keyframe's thin one), a legend
    of every layer in the colour the scene draws it with, and the list of the detail frames, whose button moves the
    timeline there; the view starts behind the car and follows it."""
    import cv2

    v = detail_viewer
    page = browser.new_page()
    page.goto(f"http://127.0.0.1:{v.port}")
    page.get_by_text("Connected").wait_for(timeout=30000)
    legend = page.locator(".plvo-legend")
    legend.wait_for(timeout=10000)
    text = legend.inner_text()
    assert all(label in text for label, _ in LAYERS.values()), text
    for key in ("map_lines", "est", "loops", "gt"):
        style = legend.locator(f'[data-layer="{key}"] span').first.get_attribute("style").replace(" ", "")
        assert _css(LAYER_COLORS[key]).replace(" ", "") in style, (key, style)
    panel = _until(lambda: page.evaluate(_PANEL_IMAGES), lambda imgs: len(imgs) == 1)
    assert len(panel) == 1 and panel[0][:2] == [v.limits.panel_image_width, 96], panel  # the fake's 1200 x 360
    assert v.image_caption.content == "frame 0 (full detail)"

    client = next(iter(v.server.get_clients().values()))
    assert _wait(lambda: np.linalg.norm(client.camera.look_at - pose(0)[:3, 3]) < 12.5)  # behind the car, at it
    v.slider.value = 16  # between detail frames: keyframe 15's thin image
    page.get_by_text("frame 15 (its keyframe's, thinned)").wait_for(timeout=10000)
    panel = _until(lambda: page.evaluate(_PANEL_IMAGES), lambda imgs: imgs and imgs[0][1] == 96)
    x, y, w, h = (round(c) for c in panel[0][2:])
    page.screenshot(path=str(tmp_path / "panel.png"))
    shot = cv2.imread(str(tmp_path / "panel.png"))[y:y + h, x:x + w]
    assert shot.size and shot.std() > 10, "the image panel looks blank"  # the fake's noise and white block
    p16 = pose(16)[:3, 3]  # followed: the same view of the car as at frame 0 (18 m behind, 14 m above)
    assert _wait(lambda: abs(np.linalg.norm(client.camera.position - p16) - np.hypot(18, 14)) < 0.5), \
        client.camera.position

    label = next(k for k, a in v._detail_options.items() if a == 21)  # keyframe 8, 1 in 4
    page.get_by_role("combobox").click()
    page.get_by_role("option", name=label).click()
    assert _wait(lambda: v.detail_pick.value == label)
    page.get_by_role("button", name="Go to these frames").click()
    assert _wait(lambda: v.shown_frame == 21), v.shown_frame
    page.get_by_text("full detail: keyframe 8 (1 in 4)").wait_for(timeout=10000)
    assert v.image_caption.content == "frame 21 (full detail)"
    page.close()


def test_live_recorder_follows_the_run():
    viewer = ViserViewer(SceneStore(), port=_free_port(), live=True)
    try:
        rec = ViserRecorder(viewer, min_interval_s=0.0)
        drive(rec, N)
        rec.close()
        assert viewer.store.frames == list(range(N)) and viewer.shown_frame == N - 1
        assert viewer.slider.max == N - 1 and viewer.slider.value == N - 1
        assert {"scan", "map_points", "map_lines", "graph", "keyframes", "loops", "gt", "est", "camera"} <= set(
            viewer._handles)
        pts = viewer._handles["scan"].points
        assert pts.dtype == np.float32  # float16 would quantise KITTI-scale positions
        viewer.slider.value = 2  # the user goes back: following stops
        assert viewer.shown_frame == 2 and not viewer.follow.value
    finally:
        viewer.close()


# In the page: from the key event (its own timestamp, so the time it waited for a busy main thread counts) to the
# start of the render frame after the one in which the new frame's status reached the DOM. The status comes in one
# websocket window with the scene it describes and is applied in the render frame that draws that scene, so the next
# frame starts once that one was handed to the compositor: what a user sees. Playwright's own round trips (the key
# press waits for the page to acknowledge it, a predicate is polled on timers that wait behind render frames) are
# not: they took ~170 ms of ~450 on a loaded 2-core machine, and are printed apart. The camera's image comes later:
# viser's page loads it as a texture asynchronously, in tasks that wait behind render frames; it is timed apart, by
# the texture on the camera node (viser's own end-to-end hook, window.__viserMutable), polled between frames.
_STEP_PROBE = """() => {
    const shown = () => (document.body.textContent.match(/\\((\\d+)\\/4541\\)/) || [])[1];
    const texture = () => {
        let t = null;
        const camera = window.__viserMutable.nodeRefFromName['/camera'];
        camera?.traverse(o => { if (o.material?.map) t = o.material.map.uuid; });
        return t;
    };
    window.__lat = []; window.__img = []; window.__shown = null;
    let down = null, last = shown(), tex = texture();
    setInterval(() => {
        const now = texture();
        if (now === tex) return;
        tex = now;
        requestAnimationFrame(() => window.__img.push(performance.now() - down));
    }, 5);
    document.addEventListener('keydown', e => { down = e.timeStamp; }, true);
    new MutationObserver(() => {
        const now = shown();
        if (!now || now === last) return;
        last = now;
        requestAnimationFrame(() => { window.__lat.push(performance.now() - down); window.__shown = +now; });
    }).observe(document.body, {subtree: true, childList: true, characterData: true});
}"""


def test_frame_change_on_a_long_replay(browser, tmp_path_factory):
    """A 4541-frame replay (a whole KITTI 00's length) opens from its index, and a frame change reaches the page.
    Measured: the server's share (slider update to scene sent), the time in the page from a key press on the slider
    to the new frame on screen and to its image (see _STEP_PROBE), and the whole round trip through playwright. Each
    step waits for the image before the next key, as a user stepping through frames would."""
    from app_fakes import long_pose, write_long_recording

    path = tmp_path_factory.mktemp("long") / "long.rrd"
    write_long_recording(path, 4541, every=6)
    t0 = time.perf_counter()
    store = load_rrd(path)
    opened_s = time.perf_counter() - t0
    assert len(store.frames) == 4541 and len(store._cache) == 0  # nothing decoded before it is shown
    v = ViserViewer(store, port=_free_port())
    server_s: list[float] = []
    show = v.show

    def timed_show(*args, **kwargs):
        t = time.perf_counter()
        show(*args, **kwargs)
        server_s.append(time.perf_counter() - t)

    v.show = timed_show
    try:
        page = browser.new_page()
        page.goto(f"http://127.0.0.1:{v.port}")
        page.get_by_text("Connected").wait_for(timeout=30000)
        v.slider.value = 3000
        page.get_by_text("(3001/4541)").wait_for(timeout=20000)
        page.evaluate(_STEP_PROBE)
        page.wait_for_timeout(1500)  # frame 3001's image, still loading, is not the first step's
        page.evaluate("window.__img.length = 0")
        page.get_by_role("slider").first.focus()
        server_s.clear()
        times = []
        for step in range(1, 13):  # frame by frame: a new image and pose each time, a new scan every 6
            t0 = time.perf_counter()
            page.keyboard.press("ArrowRight")
            page.wait_for_function(f"window.__shown === {3001 + step}", polling=10, timeout=10000)
            times.append(time.perf_counter() - t0)
            page.wait_for_function(f"window.__img.length === {step}", polling=10, timeout=10000)  # then the next
        in_page, image = page.evaluate("window.__lat"), page.evaluate("window.__img")
        assert v.shown_frame == 3012 and len(in_page) == 12 and len(image) == 12, (in_page, image)
        np.testing.assert_allclose(v._handles["camera"].position, long_pose(3012)[:3, 3], atol=1e-2)
        page_ms, trip_ms, server_ms = np.median(in_page), 1e3 * np.median(times), 1e3 * np.median(server_s)
        print(f"\nlong replay: opened in {opened_s:.2f} s; frame change: server {server_ms:.1f} ms, on the page "
              f"{page_ms:.0f} ms (median of {len(in_page)}, max {max(in_page):.0f} ms), its image "
              f"{np.median(image):.0f} ms; through playwright {trip_ms:.0f} ms")
        assert server_ms < 100, server_s
        # Not 100 ms as on a GPU: in headless Chromium every render frame is drawn in software (SwiftShader) and read
        # back for the compositor, ~25 ms for an empty scene at this viewport and ~35 with this one, and a frame change
        # waits for ~4 of them (the key event behind one, the websocket reply behind one or two, the one that draws
        # it); with the canvas hidden the same steps took ~65 ms, playwright's round trip included. ~240 ms here on a
        # loaded 2-core machine (~350 with world-unit lines and strided trajectories); the bound leaves room for a
        # busier one. The image follows ~150 ms later (see _STEP_PROBE) and is not bounded but by the wait above.
        assert page_ms < 500, in_page
        page.close()
    finally:
        v.close()


def test_a_restarted_run_grows_again_from_the_first_frame():
    """System.restart: the live scene of the frames so far is dropped, the run started again shown as it grows,
    and the log says why."""
    from app_fakes import restart_info

    viewer = ViserViewer(SceneStore(), port=_free_port(), live=True)
    try:
        rec = ViserRecorder(viewer, min_interval_s=0.0)
        drive(rec, 6)
        rec.on_restart(restart_info(N, 5))
        assert viewer.store.frames == [] and "est" not in viewer.store.layers
        drive(rec, 3, start=False)
        assert viewer.store.frames == [0, 1, 2] and viewer.shown_frame == 2
        assert viewer.store.latest("log", 0).startswith("started again from the first frame: camera-lidar time "
                                                        "offset found at frame 5")
        np.testing.assert_allclose(np.asarray(viewer.store.latest("est", 2))[-1], pose(2)[:3, 3], atol=1e-5)
    finally:
        viewer.close()


def test_live_store_stays_bounded():
    """Over a long live run only the last `keep` images and scans are kept whole, older maps thinned, and the
    estimate is a view of one trail rather than a copy a keyframe."""
    from plvo_app.viser_viewer import TrailView

    viewer = ViserViewer(SceneStore(), port=_free_port(), live=True)
    try:
        rec = ViserRecorder(viewer, min_interval_s=1e9, keep=2)
        drive(rec, N)
        s = viewer.store
        images = [s.value_at("image", f) for f in range(N)]
        assert sum(v is not None for v in images) == 2 and images[-1] is not None
        scans = [v for v in s.layers["scan"][1] if v is not None]
        assert len(scans) == 2 and s.count("scan") == 4  # every keyframe still has its entry
        maps = s.layers["map_points"][1]
        assert [len(m) for m in maps] == [20, 40, 600, 800]  # the fake's 200 a keyframe; older ones tenfold fewer
        est = s.layers["est"][1]
        assert all(isinstance(e, TrailView) for e in est)
        np.testing.assert_allclose(np.asarray(est[-1])[-1], pose(N - 1)[:3, 3], atol=1e-5)
    finally:
        viewer.close()
