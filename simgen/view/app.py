"""The browser viewer of ``simgen view``: a viser server showing a :class:`~simgen.view.sources.Scene`.

viser serves its own web client (three.js), so this module only builds the scene and the GUI:

- the selection dropdowns of the source (garment, shape, motion, ...), which load another scene;
- playback: play/pause, a frame slider, the playback rate [frames/s];
- the garment colouring (:mod:`simgen.view.measures`: error against the reference, strain, distance to
  the body) with its full-colour scale;
- the per-frame physics terms of every track as a uPlot chart beside the scene, computed in a
  background thread once a scene is shown, and the current frame's values as text.

Bodies are drawn with the role colour of :data:`simgen.io.usd.ROLE_COLORS` (skin), garments in theirs
(blue) unless coloured by a field; each track sits at its offset (side by side along +X). The floor
(y = 0) is a grid. Y is up, units are metres.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from simgen.errors import InputError
from simgen.io.usd import ROLE_COLORS
from simgen.view.measures import (DEFAULT_SCALES, FIELD_UNITS, TERMS, available_fields, body_distance, field_colors,
                                  frame_terms, vertex_error, vertex_strain)

__all__ = ["Viewer", "serve", "BODY_RGB", "GARMENT_RGB"]

BODY_RGB = tuple(int(round(255 * c)) for c in ROLE_COLORS["body"])
GARMENT_RGB = tuple(int(round(255 * c)) for c in ROLE_COLORS["garment"])
#: Line colours of the tracks in the terms plot (uPlot CSS colours), in track order.
#: Strength of the environment lighting (viser's default 1.0 renders skin and blue near white).
ENVIRONMENT_INTENSITY = 0.35
PLOT_HEIGHT = 180  # [px]
PLOT_COLORS = ("#2a2a2a", "#e8590c", "#7048e8", "#2b8a3e", "#c2255c")


class _Cancelled(Exception):
    """Raised from the terms' progress callback to stop computing them."""


class Viewer:
    """A viser server for one :class:`~simgen.view.sources.Source`.

    selection: preselected values of the source's keys (None: defaults); host, port: where to serve
    (viser takes the next free port if ``port`` is taken: see :attr:`url`); ``start()`` loads the
    first scene and serves it, ``stop()`` shuts the server down.
    """

    def __init__(self, source, *, selection: dict | None = None, host: str = "127.0.0.1", port: int = 8080,
                 verbose: bool = False) -> None:
        self.source = source
        self.selection = source.select(selection)
        self.host, self.port, self.verbose = host, int(port), verbose
        self.server = None
        self.scene = None
        self.terms: dict = {}
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._playing = False
        self._syncing = False
        self._generation = 0
        self._cache: dict = {}
        self._bodies: dict = {}
        self._garments: dict = {}
        self._plot = None
        self._player = None
        self._terms_thread = None

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.server.get_port() if self.server else self.port}"

    def start(self) -> "Viewer":
        """Load the selected scene, start serving it and the playback thread; returns self."""
        import viser

        scene = self.source.load(self.selection)  # bad input fails here, before a port is opened
        self.server = viser.ViserServer(host=self.host, port=self.port, verbose=self.verbose)
        self.server.scene.set_up_direction("+y")
        # The default environment map at full intensity washes the role colours out to near white.
        self.server.scene.configure_environment_map("warehouse", environment_intensity=ENVIRONMENT_INTENSITY)
        self._build_gui(scene)
        self._show(scene, frame_camera=True)
        self._player = threading.Thread(target=self._play_loop, name="simgen-view-play", daemon=True)
        self._player.start()
        return self

    def stop(self) -> None:
        """Stop playback and the server (background work still running draws nothing more)."""
        self._stop.set()
        for thread in (self._player, self._terms_thread):  # the terms stop at their next chunk of frames
            if thread is not None:
                thread.join(timeout=60)
        with self._lock:
            if self.server is not None:
                self.server.stop()

    # ------------------------------------------------------------------------------ GUI
    def _build_gui(self, scene) -> None:
        gui = self.server.gui
        gui.configure_theme(show_share_button=False)
        gui.main_panel.dock_right()
        self.info = gui.add_markdown("")
        self.dropdowns = {}
        if self.source.keys:
            with gui.add_folder("Selection"):
                options = self._options(self.selection)
                for key in self.source.keys:
                    dd = gui.add_dropdown(key, options[key], initial_value=self.selection[key])
                    dd.on_update(lambda _e, k=key: self._on_select(k))
                    self.dropdowns[key] = dd
        with gui.add_folder("Playback"):
            self.play = gui.add_button("Play")
            self.play.on_click(lambda _e: self._toggle_play())
            self.slider = gui.add_slider("frame", 0, max(scene.num_frames - 1, 0), 1, 0)
            self.slider.on_update(lambda _e: self._draw())
            self.rate = gui.add_number("frames/s", initial_value=float(scene.fps), min=0.5, max=240.0, step=0.5)
        with gui.add_folder("Colour"):
            self.field = gui.add_dropdown("colour by", ("none",), initial_value="none")
            self.field.on_update(lambda _e: self._on_field())
            self.scale = gui.add_number("scale", initial_value=0.04, min=1e-6, step=0.005)
            self.scale.on_update(lambda _e: self._draw())
            self.legend = gui.add_markdown("")
        self.terms_folder = gui.add_folder("Physics terms")
        with self.terms_folder:
            self.term = gui.add_dropdown("term", TERMS, initial_value="potential")
            self.term.on_update(lambda _e: self._update_plot())
            self.terms_text = gui.add_markdown("")

    def _options(self, selection: dict) -> dict:
        """The options of every key, each computed with the keys before it as selected."""
        out, partial = {}, {}
        for key in self.source.keys:
            out[key] = self.source.choices(partial)[key]
            partial[key] = selection.get(key) if selection.get(key) in out[key] else (out[key] or [None])[0]
        return out

    def _on_select(self, key: str) -> None:
        """A dropdown changed: refresh the later dropdowns' options, then load the scene (in a thread)."""
        if self._syncing:
            return
        wanted = {k: dd.value for k, dd in self.dropdowns.items()}
        options = self._options(wanted)
        self._syncing = True
        try:
            for k, dd in self.dropdowns.items():
                dd.options = tuple(options[k])
                if dd.value not in options[k] and options[k]:
                    dd.value = options[k][0]
        finally:
            self._syncing = False
        self.selection = {k: dd.value for k, dd in self.dropdowns.items()}
        self.info.content = f"loading {', '.join(self.selection.values())} ..."
        threading.Thread(target=self._load, args=(dict(self.selection),), daemon=True).start()

    def _load(self, selection: dict) -> None:
        try:
            scene = self.source.load(selection)
        except Exception as exc:
            self.info.content = f"**could not load:** {exc}"
            if isinstance(exc, InputError):
                return
            raise  # a bug: its traceback goes to the terminal
        self._show(scene)

    def _toggle_play(self) -> None:
        self._playing = not self._playing
        self.play.label = "Pause" if self._playing else "Play"

    def _on_field(self) -> None:
        name = self.field.value
        if name in DEFAULT_SCALES:
            self._syncing = True
            self.scale.value = DEFAULT_SCALES[name]
            self._syncing = False
        self._draw()

    # ------------------------------------------------------------------------------ scene
    def _show(self, scene, *, frame_camera: bool = False) -> None:
        """Replace the drawn scene: bodies, garments, GUI ranges; start computing its terms."""
        from simgen.physics import ClothRest

        with self._lock:
            if self._stop.is_set():
                return
            for handle in [*self._bodies.values(), *self._garments.values()]:
                handle.remove()
            self.scene, self.terms, self._cache, self._garments = scene, {}, {}, {}
            self._generation += 1
            self._rest = (ClothRest.from_mesh(scene.rest, scene.garment_faces, scene.material or "cotton")
                          if scene.rest is not None else None)
            self._bodies = {t.label: self.server.scene.add_mesh_simple(
                f"/tracks/{t.label}/body", scene.body_vertices[0], scene.body_faces, color=BODY_RGB,
                position=tuple(float(x) for x in t.offset)) for t in scene.tracks}
            self._reset_controls(scene)
            if frame_camera:
                self._frame_camera(scene)
            self._draw()
        self._terms_thread = threading.Thread(target=self._compute_terms, args=(scene, self._generation), daemon=True)
        self._terms_thread.start()

    def _reset_controls(self, scene) -> None:
        self._syncing = True
        try:
            self.slider.max = max(scene.num_frames - 1, 0)
            self.slider.value = min(int(self.slider.value), scene.num_frames - 1)
            self.rate.value = float(scene.fps)
            fields = available_fields(scene)
            self.field.options = tuple(fields)
            if self.field.value not in fields:
                self.field.value = "none"
        finally:
            self._syncing = False
        extra = f"; error against **{scene.reference}**" if scene.reference else ""
        self.info.content = (f"**{scene.title}**  \n{scene.num_frames} frames at {scene.fps:g} fps; tracks: "
                             f"{', '.join(scene.labels)}{extra}")
        self.terms_text.content = "computing the physics terms ..." if scene.rest is not None else \
            "no physics terms (the garment's rest shape is unknown)"

    def _frame_camera(self, scene) -> None:
        """Camera for new clients: in front of (+Z) all tracks, looking at their middle; the floor grid."""
        lo = np.min([scene.body_vertices[0].min(0) + t.offset for t in scene.tracks], axis=0)
        hi = np.max([scene.body_vertices[0].max(0) + t.offset for t in scene.tracks], axis=0)
        centre = (lo + hi) / 2
        size = max(hi[0] - lo[0], hi[1] - lo[1], 0.5)
        self.server.initial_camera.look_at = tuple(float(x) for x in centre)
        self.server.initial_camera.position = (float(centre[0]), float(centre[1] + 0.1 * size),
                                               float(centre[2] + 1.05 * size))
        self.server.scene.add_grid("/floor", width=float(hi[0] - lo[0]) + 2.0, height=2.0 + float(hi[2] - lo[2]),
                                   plane="xz", position=(float(centre[0]), 0.0, float(centre[2])))

    def _draw(self) -> None:
        """Draw the slider's frame: every track's body and garment (coloured by the chosen field)."""
        import trimesh

        if self._syncing or self.scene is None or self._stop.is_set():
            return
        with self._lock:
            scene, f = self.scene, min(int(self.slider.value), self.scene.num_frames - 1)
            for t in scene.tracks:
                self._bodies[t.label].vertices = scene.body_vertices[f]
                rgba = np.full((t.positions.shape[1], 4), 255, dtype=np.uint8)
                rgba[:, :3] = np.clip(np.round(self._colors(t.label, f) * 255), 0, 255)
                mesh = trimesh.Trimesh(t.positions[f], scene.garment_faces, vertex_colors=rgba, process=False)
                self._garments[t.label] = self.server.scene.add_mesh_trimesh(
                    f"/tracks/{t.label}/garment", mesh, position=tuple(float(x) for x in t.offset))
            self._show_legend()
            self._show_frame_terms(f)

    def _colors(self, label: str, frame: int) -> np.ndarray:
        """RGB in [0, 1] (V, 3) of a track's garment at a frame for the chosen field (values cached)."""
        name, scene = self.field.value, self.scene
        if name == "none":
            return np.tile(np.asarray(GARMENT_RGB, dtype=np.float32) / 255, (scene.tracks[0].positions.shape[1], 1))
        key = (name, label, frame)
        if key not in self._cache:
            x = scene.track(label).positions[frame]
            self._cache[key] = (vertex_error(scene, label, frame) if name == "error" else
                                vertex_strain(x, self._rest) if name == "strain" else
                                body_distance(x, scene.body_vertices[frame], scene.body_faces))
        return field_colors(name, self._cache[key], float(self.scale.value))

    def _show_legend(self) -> None:
        name, scale = self.field.value, float(self.scale.value)
        if name == "none":
            self.legend.content = ""
        elif name == "distance":
            self.legend.content = f"distance [m]: red inside (<= -{scale:g}), white on the body, blue >= {scale:g}"
        else:
            self.legend.content = f"{name} [{FIELD_UNITS[name]}]: light grey at 0, red at {scale:g} and above"

    # ------------------------------------------------------------------------------ physics terms
    def _compute_terms(self, scene, generation: int) -> None:
        """Background: the scene's terms, then the chart (unless another scene came meanwhile)."""
        def progress(done: int, total: int) -> None:
            if self._stop.is_set() or generation != self._generation:
                raise _Cancelled
            self.terms_text.content = f"computing the physics terms ... {100 * done // max(total, 1)}%"

        try:
            terms, failure = frame_terms(scene, progress=progress), None
        except _Cancelled:
            return
        except Exception as exc:  # noqa: BLE001 - shown in the GUI; the scene stays usable without terms
            terms, failure = {}, f"no physics terms: {exc}"
        with self._lock:
            if generation != self._generation or self._stop.is_set():
                return
            self.terms = terms
            if failure:
                self.terms_text.content = failure
            self._update_plot()
            self._show_frame_terms(min(int(self.slider.value), scene.num_frames - 1))

    def _update_plot(self) -> None:
        """(Re)draw the chart of the chosen term for every track against time [s]."""
        with self._lock:
            self._replace_plot()

    def _replace_plot(self) -> None:
        if self._plot is not None:
            self._plot.remove()
            self._plot = None
        if not self.terms:
            return
        scene, term = self.scene, self.term.value
        ys = [np.asarray(self.terms[t.label][term], dtype=np.float64) for t in scene.tracks]
        ok = np.flatnonzero(np.all([np.isfinite(y) for y in ys], axis=0))
        if len(ok) == 0:
            return
        first = int(ok[0])
        x = np.arange(first, scene.num_frames, dtype=np.float64) / scene.fps
        series = [{"label": "t [s]"}] + [{"label": t.label, "stroke": PLOT_COLORS[k % len(PLOT_COLORS)], "width": 2}
                                         for k, t in enumerate(scene.tracks)]
        with self.terms_folder:
            self._plot = self.server.gui.add_uplot(
                (x, *[np.nan_to_num(y[first:]) for y in ys]), tuple(series), title=f"{term} [J per frame]",
                scales={"x": {"time": False}}, height=PLOT_HEIGHT)

    def _show_frame_terms(self, frame: int) -> None:
        if not self.terms:
            return
        term = self.term.value
        values = ", ".join(f"{label} {float(v[term][frame]):.4g}" if np.isfinite(v[term][frame]) else f"{label} n/a"
                           for label, v in self.terms.items())
        self.terms_text.content = f"frame {frame} ({frame / self.scene.fps:.2f} s), {term} [J]: {values}"

    # ------------------------------------------------------------------------------ playback
    def _play_loop(self) -> None:
        while not self._stop.is_set():
            start = time.perf_counter()
            if self._playing and self.scene is not None and self.scene.num_frames > 1:
                self.slider.value = (int(self.slider.value) + 1) % self.scene.num_frames
            period = 1.0 / max(float(self.rate.value), 0.5)
            self._stop.wait(max(0.0, period - (time.perf_counter() - start)))


def _check_host(host: str) -> None:
    """InputError unless HOST is an address this machine can serve on (viser would retry forever)."""
    import socket

    try:
        family = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0][0]
        with socket.socket(family, socket.SOCK_STREAM) as sock:
            sock.bind((host, 0))
    except OSError as exc:
        raise InputError(f"--host {host!r} is not an address of this machine ({exc.strerror or exc})") from None


def serve(path, *, host: str = "127.0.0.1", port: int = 8080, garment: str | None = None, shape: str | None = None,
          motion: str | None = None, echo=print, block: bool = True) -> Viewer:
    """Open PATH (:func:`simgen.view.sources.open_source`) and serve it at http://HOST:PORT until
    Ctrl-C (``block=False``: return the running :class:`Viewer`). garment/shape/motion preselect
    the dropdowns; InputError for a bad path or value."""
    from simgen.view.sources import open_source

    if not 0 <= int(port) < 65536:
        raise InputError(f"--port must be between 0 (any free port) and 65535, got {port}")
    _check_host(host)
    source = open_source(path)
    viewer = Viewer(source, selection={"garment": garment, "shape": shape, "motion": motion}, host=host,
                    port=port).start()
    echo(f"simgen view: {viewer.url} ({source.kind} {path}; Ctrl-C stops)")
    if not block:
        return viewer
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    return viewer
