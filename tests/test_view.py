"""`simgen view`: each kind of input loads into the viewer's scene (the right arrays), bad input is
one sentence, the measures come from the packages that own them, the GUI reloads and recolours,
and the page drawn by a real browser (headless Chromium, WebGL on SwiftShader) shows the body and
the garment in their colours.

Data: the `tiny` dataset preset (simulated here, ~10 s), a short CPU simulation of tshirt_1k (its
.npz and a USD written like `simgen simulate` writes it), and an `eval garment` folder of a fit-only
model trained for a few epochs on the tiny store.
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from simgen.errors import InputError
from simgen.view.sources import DatasetSource, EvalGarmentSource, SimulationSource, UsdSource, open_source

CHROMIUM = Path("/usr/bin/chromium")


# ------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def store(tmp_path_factory):
    from simgen.dataset import generate_dataset

    out = tmp_path_factory.mktemp("view_store") / "tiny"
    generate_dataset("tiny", out=str(out))
    return out


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """tshirt_1k on walk_fast after a short start protocol: the .npz and a USD of body + garment."""
    from simgen.io.usd import MeshTrack, write_usd
    from simgen.sim import SimulationConfig, simulate

    folder = tmp_path_factory.mktemp("view_sim")
    cfg = SimulationConfig(relax_frames=3, ramp_frames=5, rest_frames=2, device="cpu", record_body=True)
    result = simulate("tshirt_1k", "open", "walk_fast", None, cfg, frames=4)
    npz = result.save_npz(folder / "tshirt_1k_walk_fast.npz")
    tracks = [MeshTrack(name="body", points=result.body_vertices, faces=result.body_faces, role="body"),
              MeshTrack(name="tshirt_1k", points=result.positions, faces=result.faces, role="garment")]
    usd = write_usd(folder / "tshirt_1k_walk_fast.usdc", tracks, fps=result.fps,
                    metadata={"garment": "tshirt_1k", "motion": "walk_fast"})
    return npz, usd


@pytest.fixture(scope="module")
def eval_folder(store, tmp_path_factory):
    """`eval garment` output of a fit-only model (5 epochs) on the tiny store."""
    from simgen.learn import FitConfig, load_garment_data, make_split, train_fit
    from simgen.learn.evaluate import evaluate_garment

    root = tmp_path_factory.mktemp("view_eval")
    data = load_garment_data(store)
    train_fit(data, root / "model", make_split(data, "motion"), config=FitConfig(epochs=5))
    evaluate_garment(root / "model", data, root / "eval", timing=False, plots=False, physics_sequences=0,
                     inside_stride=5)
    return root / "eval"


def one_sentence(exc: Exception) -> str:
    text = str(exc)
    assert "\n" not in text and len(text) < 300, text
    return text


# ------------------------------------------------------------------------------------ sources
def test_a_simulation_npz_loads_its_body_and_garment(simulated):
    npz, _ = simulated
    src = open_source(npz)
    assert isinstance(src, SimulationSource) and src.keys == ()
    scene = src.load(src.select())
    with np.load(npz) as d:
        np.testing.assert_array_equal(scene.tracks[0].positions, d["positions"])
        np.testing.assert_array_equal(scene.body_vertices, d["body_vertices"])
        np.testing.assert_array_equal(scene.body_faces, d["body_faces"])
        np.testing.assert_array_equal(scene.garment_faces, d["faces"])
    assert scene.labels == ["simulation"] and scene.reference is None and scene.num_frames == 4
    assert scene.rest.shape == scene.tracks[0].positions.shape[1:] and scene.material is not None


def test_a_usd_file_gives_the_same_scene_as_its_npz(simulated):
    npz, usd = simulated
    a = open_source(npz).load({})
    src = open_source(usd)
    assert isinstance(src, UsdSource)
    b = src.load(src.select())
    assert b.labels == ["tshirt_1k"] and b.num_frames == a.num_frames and b.fps == a.fps
    np.testing.assert_allclose(b.tracks[0].positions, a.tracks[0].positions, atol=1e-6)
    np.testing.assert_allclose(b.body_vertices, a.body_vertices, atol=1e-6)
    np.testing.assert_array_equal(b.tracks[0].offset, 0)
    np.testing.assert_allclose(b.rest, a.rest)  # the garment named in the metadata: strain and terms work


def test_a_dataset_store_offers_garment_shape_motion(store):
    from simgen.dataset import open_dataset

    src = open_source(store)
    assert isinstance(src, DatasetSource) and src.keys == ("garment", "shape", "motion")
    assert src.choices({}) == {"garment": ["tshirt_1k"], "shape": ["zero", "b1p2"],
                               "motion": ["jumping_jacks", "walk_fast"]}
    selection = src.select({"shape": "b1p2", "motion": "walk_fast"})
    scene = src.load(selection)
    ds = open_dataset(store)
    seq = ds.sequence("walk_fast__b1p2")
    np.testing.assert_array_equal(scene.tracks[0].positions, seq["garment_vertices"])
    body = ds.load_body()
    posed = body.forward_sequence(seq["betas"], seq["poses"], seq["trans"]).vertices
    np.testing.assert_allclose(scene.body_vertices, posed, atol=1e-6)
    np.testing.assert_array_equal(scene.rest, ds.template["garment_template"])
    assert scene.num_frames == 5 and scene.contact.stiffness > 0
    with pytest.raises(InputError, match="--motion 'dance'.*jumping_jacks, walk_fast"):
        src.select({"motion": "dance"})


def test_a_folder_of_stores_lists_each_garment(store, tmp_path):
    shutil.copytree(store, tmp_path / "stores" / "tshirt_1k")
    src = open_source(tmp_path / "stores")
    assert isinstance(src, DatasetSource) and src.choices({})["garment"] == ["tshirt_1k"]
    with pytest.raises(InputError, match="--garment 'dress'"):
        src.select({"garment": "dress"})


def test_an_eval_folder_shows_ground_truth_model_and_lbs_side_by_side(eval_folder, store):
    from simgen.dataset import open_dataset
    from simgen.view.measures import available_fields, vertex_error

    src = open_source(eval_folder)
    assert isinstance(src, EvalGarmentSource) and src.keys == ("motion", "shape")
    selection = src.select()
    assert selection["motion"] == "walk_fast"  # the held-out motion first
    scene = src.load(selection)
    assert scene.labels == ["ground_truth", "ours", "lbs"] and scene.reference == "ground_truth"
    gt = open_dataset(store).sequence(f"walk_fast__{selection['shape']}")["garment_vertices"]
    np.testing.assert_allclose(scene.track("ground_truth").positions, gt, atol=1e-5)
    xs = [t.offset[0] for t in scene.tracks]
    assert xs[0] == 0 and 0.9 < xs[1] < xs[2]  # side by side along +X, the bodies 1 m+ apart
    assert np.all(np.abs([t.offset[1:] for t in scene.tracks]) < 1e-6)
    err = vertex_error(scene, "lbs", 2)
    assert err.shape == (gt.shape[1],) and 0 < err.mean() < 0.2
    assert available_fields(scene) == ["none", "error", "strain", "distance"]


@pytest.mark.parametrize("case", ["missing", "other_file", "bad_npz", "metrics_without_model"])
def test_bad_paths_are_one_sentence_naming_the_file(case, tmp_path):
    path = tmp_path / {"missing": "nothing.npz", "other_file": "notes.txt", "bad_npz": "broken.npz",
                       "metrics_without_model": "eval"}[case]
    if case == "other_file":
        path.write_text("hello")
    elif case == "bad_npz":
        path.write_bytes(b"PK\x03\x04 not a zip archive")
    elif case == "metrics_without_model":
        path.mkdir()
        (path / "metrics.json").write_text(json.dumps({"model_dir": str(tmp_path / "gone"), "dataset": str(tmp_path),
                                                      "sequences": {}}))
    with pytest.raises(InputError) as info:
        src = open_source(path)
        src.load(src.select())
    text = one_sentence(info.value)
    assert path.name in text or str(path) in text


def test_a_preselection_the_input_does_not_have_is_refused(simulated):
    with pytest.raises(InputError, match="--garment does not apply to .*tshirt_1k_walk_fast.npz"):
        open_source(simulated[0]).select({"garment": "tshirt_1k"})


# ------------------------------------------------------------------------------------ measures
def test_measures_come_from_physics_and_the_body_query(simulated):
    import torch

    from simgen.physics import ClothRest
    from simgen.view.measures import body_distance, field_colors, frame_terms, vertex_strain

    scene = open_source(simulated[0]).load({})
    rest = ClothRest.from_mesh(scene.rest, scene.garment_faces, scene.material, dtype=torch.float64)
    assert np.abs(vertex_strain(scene.rest, rest)).max() < 1e-9  # no stretch at the rest shape
    stretched = vertex_strain(scene.rest * 1.1, rest)
    np.testing.assert_allclose(stretched, 0.1, atol=1e-9)  # uniform 10% stretch: principal stretch - 1
    d = body_distance(scene.tracks[0].positions[-1], scene.body_vertices[-1], scene.body_faces)
    assert d.shape == (scene.rest.shape[0],) and np.median(d) > 0 and d.max() < 0.2
    assert field_colors("distance", d, 0.02).shape == (len(d), 3)
    terms = frame_terms(scene)["simulation"]
    assert {"strain", "bending", "gravity", "inertia", "collision", "potential"} <= set(terms)
    assert np.isnan(terms["inertia"][:2]).all() and np.isfinite(terms["potential"][2:]).all()


# ------------------------------------------------------------------------------------ the app
def wait_for(condition, timeout=60.0):
    end = time.time() + timeout
    while time.time() < end:
        if condition():
            return True
        time.sleep(0.1)
    return False


@pytest.fixture
def viewer(store):
    from simgen.view import Viewer

    v = Viewer(open_source(store), selection={"shape": "zero"}, port=0).start()
    yield v
    v.stop()


def test_the_gui_reloads_recolours_and_plots_the_terms(viewer):
    assert viewer.scene.meta["sequence"] == "jumping_jacks__zero"
    assert wait_for(lambda: viewer.terms), "the physics terms were not computed"
    assert viewer._plot is not None
    viewer.dropdowns["motion"].value = "walk_fast"
    assert wait_for(lambda: viewer.scene.meta["sequence"] == "walk_fast__zero")
    assert tuple(viewer.field.options) == ("none", "strain", "distance")
    viewer.field.value = "distance"
    viewer.slider.value = 3
    assert ("distance", "simulation", 3) in viewer._cache
    viewer._toggle_play()
    assert wait_for(lambda: viewer.slider.value != 3, timeout=10)
    viewer._toggle_play()


def colour_mask(img: np.ndarray, rgb, tol: float = 0.12) -> np.ndarray:
    """Pixels whose chromaticity (r, g, b) / (r + g + b) is within ``tol`` of the colour's and that are
    neither near-white nor near-black: the colour under any shading of the browser's lights."""
    px = img[..., :3].astype(np.float64)
    total = px.sum(-1, keepdims=True)
    want = np.asarray(rgb, dtype=np.float64) / sum(rgb)
    lit = (total[..., 0] > 90) & (total[..., 0] < 700)
    return lit & (np.abs(px / np.maximum(total, 1) - want).max(-1) < tol * want.max())


class Chromium:
    """Headless Chromium driven over the DevTools protocol: one page, screenshots on demand. (A plain
    ``--screenshot`` fires on a virtual clock, often while viser's client is still fading the scene
    in from white.)"""

    def __init__(self, profile: Path) -> None:
        log = profile.with_suffix(".log")
        cmd = [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
               "--disable-background-networking", "--disable-component-update", "--disable-sync",
               "--use-angle=swiftshader", "--enable-unsafe-swiftshader", f"--user-data-dir={profile}",
               "--window-size=1280,720", "--remote-debugging-port=0", "about:blank"]
        with open(log, "wb") as err:
            self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
        self.ws = None
        try:
            self._attach(log)
        except BaseException:
            self.close()
            raise

    def _attach(self, log: Path) -> None:
        assert wait_for(lambda: b"DevTools listening on" in log.read_bytes(), 60), log.read_text(errors="replace")
        from websockets.sync.client import connect

        url = re.search(rb"DevTools listening on (ws://\S+)", log.read_bytes()).group(1).decode()
        self.ws, self.calls, self.session = connect(url, max_size=2**26), 0, None
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]

    def call(self, method: str, **params) -> dict:
        """One DevTools command (on the page's session once attached); its result (events are dropped)."""
        self.calls += 1
        message = {"id": self.calls, "method": method, "params": params}
        self.ws.send(json.dumps(message if self.session is None else {**message, "sessionId": self.session}))
        while True:
            reply = json.loads(self.ws.recv(timeout=60))
            if reply.get("id") == self.calls:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def open(self, url: str) -> None:
        """Navigate and wait for the load event (the page changes renderer on the way)."""
        self.call("Page.enable")
        self.call("Emulation.setDeviceMetricsOverride", width=1280, height=720, deviceScaleFactor=1, mobile=False)
        self.call("Page.navigate", url=url)
        end = time.time() + 60
        while time.time() < end and json.loads(self.ws.recv(timeout=60)).get("method") != "Page.loadEventFired":
            pass

    def screenshot(self) -> np.ndarray | None:
        """The page as RGB(A) (720, 1280, ...) uint8, or None while no page is attached."""
        import imageio.v3 as iio

        try:
            data = self.call("Page.captureScreenshot", format="png")["data"]
        except RuntimeError as exc:
            if "Not attached" in str(exc):
                return None
            raise
        return iio.imread(base64.b64decode(data), extension=".png")

    def close(self) -> None:
        if self.ws is not None:
            self.ws.close()
        os.killpg(self.proc.pid, signal.SIGTERM)
        self.proc.wait(timeout=30)


def test_the_browser_draws_the_body_and_the_garment(viewer, tmp_path):
    import imageio.v3 as iio

    from simgen.view.app import BODY_RGB, GARMENT_RGB

    if not CHROMIUM.is_file():
        pytest.skip(f"{CHROMIUM} is not installed (.ci/system-deps.sh installs it)")
    browser = Chromium(tmp_path / "profile")
    try:
        browser.open(viewer.url)
        img, body, garment, end = None, 0.0, 0.0, time.time() + 120
        while time.time() < end and not (body > 0.01 and garment > 0.004):
            time.sleep(1.0)  # until the scene is drawn and faded in (SwiftShader on a busy CPU: seconds)
            shot = browser.screenshot()
            if shot is not None:
                img, scene_area = shot, shot[:, :900, :3]  # left of the GUI panel (its buttons are blue too)
                body, garment = colour_mask(scene_area, BODY_RGB).mean(), colour_mask(scene_area, GARMENT_RGB).mean()
    finally:
        browser.close()
    assert img is not None, "no screenshot: the page never attached"
    iio.imwrite(tmp_path / "view.png", img)
    assert img.shape[:2] == (720, 1280)
    assert body > 0.01, f"body colour on {body:.2%} of the scene ({tmp_path / 'view.png'})"
    assert garment > 0.004, f"garment colour on {garment:.2%} of the scene ({tmp_path / 'view.png'})"


def test_the_command_line_refuses_bad_input_in_one_sentence(tmp_path, capsys):
    from simgen.cli import main

    for argv, needle in ((["view", str(tmp_path / "none.npz")], "none.npz"),
                         (["view", str(tmp_path), "--port", "70000"], "--port"),
                         (["view", str(tmp_path), "--host", "203.0.113.7"], "203.0.113.7")):
        with pytest.raises(SystemExit) as info:
            main(argv)
        err = capsys.readouterr().err
        assert info.value.code == 2 and needle in err and "Traceback" not in err
