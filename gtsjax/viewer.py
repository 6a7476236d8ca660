"""The run as Rerun shows it: ``--view`` (the native viewer), ``--view web`` (Rerun's
web viewer, no internet needed) and ``--view-save FILE.rrd`` on ``run``, ``replay`` and ``demo``, for
one laser or several. ``rerun-sdk`` is an optional extra (``pip install "gtsjax[viewer]"``).

``--view web`` serves the page (port 9090, ``$GTSJAX_VIEW_WEB_PORT``) and the recording it shows
(Rerun's gRPC proxy, port 9876, ``$GTSJAX_VIEW_GRPC_PORT``) on one address, ``$GTSJAX_VIEW_HOST``,
by default 127.0.0.1 (this machine only; ``0.0.0.0`` for a tablet at the field, the URL then naming
this machine), and the URL printed names that address for both. Both come from Rerun's own
executable (``rerun --serve-web --bind HOST``, started beside the command and stopped when it ends):
the SDK's ``serve_web_viewer`` binds its page to every interface with no way to narrow it
(rerun-io/rerun#5882), so that the page was reachable from the field's network while its data was
not.

What it shows, in the field frame O (entity ``field``), on the timeline ``stamp`` (the scans'
stamps, so a replayed log can be scrubbed):

* ``field/bounds``, ``field/landmarks`` (the site's, labelled by class), once;
* ``field/laser``: the laser's pose as this scan's map transformation places it (an arrow);
* ``field/scan``: the scan's returns, mapped into O by that pose;
* ``field/landmarks_seen``: where this scan saw each landmark it associated (the map position plus its
  residual), labelled with the residual in cm;
* ``field/candidates``: every candidate of the scan where its segment lies, the objects coloured by
  class, the others faint, each labelled with its class or what became of it (filtered, background,
  unlike its class's examples, off its class's envelope, beyond its class's cap:
  :data:`~gtsjax.core.pipeline.REASONS`; hover for the label);
* with several lasers, those four per laser under ``field/lasers/NAME/`` (``field/lasers/north/scan``,
  each laser's returns in a colour of its own), so that one laser's scan does not replace another's;
* ``field/tracks/CLASS_ID``: each confirmed track: an arrow along its heading, its 2-σ position
  ellipse (with the x–y covariance: tilted where the error is) and its trail, labelled ``CLASS ID``
  (``CLASS ID ROBOT`` once ``run --beliefs`` has named it);
  a track that ended is cleared;
* ``stats/latency_ms`` (live), ``stats/tracks``, ``stats/landmark_residual_cm``, ``stats/dropped``
  (live: frames the link dropped): time series; the last two per laser with several
  (``stats/landmark_residual_cm/NAME``).
"""
import atexit
import collections
import math
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .core.pipeline import REASONS
from .core.scan import Beams
from .errors import InputError
from .io.bag_out import TRACK_COLOURS, track_colour

OBJECT = REASONS.index("object")

VIEWER_EXTRA = 'pip install "gtsjax[viewer]"'
TRAIL = 100  # scans of trail drawn behind each track
SEEN_COLOUR = (0, 200, 0)  # where a scan saw the landmarks
LASER_COLOUR = (230, 150, 0)
# Rerun draws a 2-D view as an image is drawn, y down, and ignores view coordinates there (rerun-io/rerun
# #1387): the field (O) would be mirrored, the laser at y = 4 m drawn below the field and counter-
# clockwise headings turning clockwise. So the field's entities sit under ``/field``, which is the
# view's space mirrored in y (its transform from ``/``), and the view shows ``/``: y up, as the field is
# seen from above and as ``gtsjax plot`` draws it. Hovered values are still the field's own.
Y_UP = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]
CLASS_COLOURS = [(150, 150, 150), (40, 40, 40), (30, 90, 220), (200, 60, 200), (20, 160, 160)]  # by class index
FAINT = (170, 170, 170, 90)  # candidates that are not objects
_COLOURS = TRACK_COLOURS  # by track id, as the ROS bag's markers (:func:`~gtsjax.io.bag_out.track_colour`)
# Each laser's returns, by the order the lasers are first seen (the first as with one laser).
SCAN_COLOURS = [(120, 120, 120), (70, 120, 190), (190, 110, 60), (120, 160, 60), (150, 90, 170)]
WEB_HOST = "127.0.0.1"  # where --view web serves the page and the data unless $GTSJAX_VIEW_HOST says


def rerun_available() -> bool:
    """Whether the optional viewer extra is installed."""
    try:
        import rerun  # noqa: F401
    except ImportError:
        return False
    return True


def _rr():
    try:
        import rerun as rr
    except ImportError:
        raise InputError("--view", f"needs Rerun, the viewer extra: {VIEWER_EXTRA}") from None
    return rr


_colour = track_colour


def _track_label(row) -> str:
    """A track's label: its class and id, and its robot's name where the live association gave one."""
    return f"{row.cls} {row.track_id} {row.robot}" if row.robot else f"{row.cls} {row.track_id}"


def ellipse(x: float, y: float, var_x: float, var_y: float, n_sigma: float = 2.0, n: int = 32,
            cov_xy: float = 0.0) -> np.ndarray:
    """The ``n_sigma`` ellipse of a position covariance (``cov_xy`` tilts it), as a closed line strip:
    the unit circle through a square root of the covariance."""
    w, v = np.linalg.eigh(np.array([[var_x, cov_xy], [cov_xy, var_y]], np.float64))
    root = v * np.sqrt(np.maximum(w, 0.0))
    t = np.linspace(0.0, 2 * np.pi, n + 1)
    return np.array([x, y]) + n_sigma * np.stack([np.cos(t), np.sin(t)], axis=1) @ root.T


def _url_host(host: str) -> str:
    """How a URL names the address ``host`` is bound to: this machine's name for every interface (a
    tablet on the field's network reaches it so), an IPv6 address in brackets."""
    if host in ("0.0.0.0", "::"):
        return socket.gethostname()
    return f"[{host}]" if ":" in host else host


def _viewer_executable() -> str:
    """Rerun's own executable, which the wheel ships in ``rerun_cli`` (``.venv/bin/rerun`` is a
    Python wrapper around it: stopping the wrapper would leave the server running)."""
    try:
        import rerun_cli
    except ImportError:
        rerun_cli = None
    exe = None if rerun_cli is None else Path(rerun_cli.__file__).with_name("rerun")
    if exe is None or not exe.is_file():
        raise InputError("--view", f"web needs Rerun's executable, which comes with the viewer extra: {VIEWER_EXTRA}")
    return str(exe)


def _listening(host: str, port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1" if host in ("0.0.0.0", "::") else host, port), timeout=0.5):
            return True
    except OSError:
        return False


def serve_web(host: str, web_port: int, grpc_port: int, timeout: float = 20.0) -> subprocess.Popen:
    """Rerun's web viewer (its page on ``web_port``) and gRPC proxy (``grpc_port``), both bound to
    ``host``, as a process of its own, returned once both listen. It is stopped when this process
    exits (not by the terminal's Ctrl-C, which would take the data away before the command flushed it)."""
    for port in (web_port, grpc_port):
        if _listening(host, port):
            raise InputError("--view", f"web: port {port} on {host} is taken; $GTSJAX_VIEW_WEB_PORT and "
                                       "$GTSJAX_VIEW_GRPC_PORT choose others")
    err = tempfile.TemporaryFile()
    proc = subprocess.Popen([_viewer_executable(), "--serve-web", "--bind", host, "--port", str(grpc_port),
                             "--web-viewer-port", str(web_port)], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
    atexit.register(_stop, proc)
    t_end = time.monotonic() + timeout
    while not (_listening(host, grpc_port) and _listening(host, web_port)):
        if proc.poll() is not None or time.monotonic() > t_end:
            _stop(proc)
            err.seek(0)
            lines = [ln for ln in err.read().decode(errors="replace").splitlines() if ln.strip()]
            why = lines[-1].strip() if lines else f"not listening after {timeout:g} s"
            raise InputError("--view", f"web: Rerun's web viewer did not start on {host} ports {web_port} and "
                                       f"{grpc_port} ({why}); $GTSJAX_VIEW_WEB_PORT and $GTSJAX_VIEW_GRPC_PORT "
                                       "choose others")
        time.sleep(0.1)
    err.close()
    return proc


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()


class Recording:
    """A Rerun recording open on the sinks a command asked for (:func:`open_recording`): ``rec``, and
    ``url`` the web page's address (None but for ``--view web``)."""

    rec = url = server = None

    def close(self) -> None:
        """Everything logged sent on (the file written); a viewer that went away is said, not fatal."""
        try:
            self.rec.flush()
            if self.url is None:
                self.rec.disconnect()
        except RuntimeError as err:
            print(f"gtsjax: warning: the view: {str(err).splitlines()[0]}", file=sys.stderr)


class View(Recording):
    """A Rerun recording of one run. ``mode``: ``"native"`` (spawn the viewer), ``"web"`` (serve the
    web viewer on ``host``, by default ``$GTSJAX_VIEW_HOST`` or :data:`WEB_HOST`: :attr:`url` is the
    page) or ``None``; ``save``: also write an ``.rrd``."""

    def __init__(self, model, *, mode: str | None = None, save: Path | None = None, web_port: int | None = None,
                 grpc_port: int | None = None, name: str = "gtsjax", host: str | None = None):
        rr = _rr()
        self.rr, self.model = rr, model
        self.rec, self.url, self.server = open_recording(name, mode, save, self._layout(), web_port=web_port,
                                                         grpc_port=grpc_port, host=host)
        self._trails: dict[str, collections.deque] = {}
        self._lasers: list[str] = []  # the named lasers, in the order first seen (their scans' colours)
        self._landmark_names = [model.classes[int(c)] for c in np.asarray(model.site.landmark_class)]
        self._static()

    def _layout(self):
        """The field large on the left, the time series stacked on the right, the timeline below."""
        import rerun.blueprint as rrb

        series = [rrb.TimeSeriesView(origin=f"stats/{name}", name=title) for name, title in (
            ("tracks", "tracks reported"), ("landmark_residual_cm", "largest landmark residual [cm]"),
            ("latency_ms", "frame-to-GTD latency [ms] (live)"), ("dropped", "dropped frames (live)"))]
        field = rrb.Spatial2DView(origin="/", contents="/field/**", name="field (O), y up")
        return rrb.Blueprint(rrb.Horizontal(field, rrb.Vertical(*series),
                                            column_shares=[3, 1]), collapse_panels=True)

    def _static(self) -> None:
        rr, site = self.rr, self.model.site
        rr.log("field", rr.Transform3D(mat3x3=Y_UP), static=True, recording=self.rec)
        if bool(np.asarray(site.has_bounds)):
            x0, y0, x1, y1 = (float(v) for v in np.asarray(site.bounds))
            rr.log("field/bounds", rr.LineStrips2D([[(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)]],
                                                   colors=[(200, 200, 200)], radii=0.01), static=True, recording=self.rec)
        xy = np.asarray(site.landmark_xy, np.float64)
        # Named on hover only: a post seen in a scan is labelled where the scan saw it, name and residual
        # in one label (two labels at one place were drawn over each other).
        rr.log("field/landmarks", rr.Points2D(xy, radii=0.06, colors=[(110, 110, 110)], labels=self._landmark_names,
                                              show_labels=False), static=True, recording=self.rec)

    def scan(self, stamp: float, ranges, angle_min: float, angle_increment: float, out, rows, *,
             latency_ms: float | None = None, dropped: int | None = None, laser: str | None = None) -> None:
        """One scan: its returns (metres; 0 or non-finite: none), the step's output ``out`` (host or
        device arrays of one scan), its GTD rows. ``laser``: the name of the laser that took it, with
        several (its entities under ``field/lasers/NAME``); ``None`` for a one-laser run."""
        rr, rec = self.rr, self.rec
        rr.set_time("stamp", timestamp=float(stamp), recording=rec)
        if laser is None:
            base, colour, suffix = "field", SCAN_COLOURS[0], ""
        else:
            if laser not in self._lasers:
                self._lasers.append(laser)
            part = rr.escape_entity_path_part(laser)  # a name with a "/" or a space is one part
            base = f"field/lasers/{part}"
            colour = SCAN_COLOURS[self._lasers.index(laser) % len(SCAN_COLOURS)]
            suffix = f"/{part}"
        sx, sy, sth = (float(v) for v in np.asarray(out.sensor_pose))
        rr.log(f"{base}/laser", rr.Arrows2D(origins=[(sx, sy)], vectors=[(0.3 * math.cos(sth), 0.3 * math.sin(sth))],
                                            colors=[LASER_COLOUR], labels=[laser or "laser"]), recording=rec)
        r = np.asarray(ranges, np.float64)
        ok = np.isfinite(r) & (r > 0)
        a = Beams(angle_min, angle_increment, r.size).angles() + sth
        pts = np.stack([sx + r[ok] * np.cos(a[ok]), sy + r[ok] * np.sin(a[ok])], axis=1)
        rr.log(f"{base}/scan", rr.Points2D(pts, radii=0.012, colors=[colour]), recording=rec)
        seen = np.asarray(out.landmark_seen, bool)
        res = np.asarray(out.landmark_residual, np.float64)
        lm = np.asarray(self.model.site.landmark_xy, np.float64)
        err_cm = np.linalg.norm(res[seen], axis=1) * 100 if seen.any() else np.zeros(0)
        names = [n for n, s in zip(self._landmark_names, seen, strict=True) if s]
        rr.log(f"{base}/landmarks_seen", rr.Points2D(lm[seen] + res[seen], radii=0.04, colors=[SEEN_COLOUR],
                                                     labels=[f"{n} {e:.1f} cm" for n, e in zip(names, err_cm, strict=True)]),
               recording=rec)
        # Every candidate of the scan: the objects by class, the rest faint, labelled with what became of them.
        reason = np.asarray(out.cand_reason)
        shown = reason > 0
        xy = np.asarray(out.cand_xy, np.float64)[shown]
        cls = np.asarray(out.cand_class)[shown]
        why = reason[shown]
        obj = why == OBJECT
        labels = [self.model.classes[int(c)] if o else REASONS[int(w)] for c, o, w in zip(cls, obj, why, strict=True)]
        colours = [CLASS_COLOURS[int(c) % len(CLASS_COLOURS)] if o else FAINT for c, o in zip(cls, obj, strict=True)]
        rr.log(f"{base}/candidates", rr.Points2D(xy if xy.size else np.zeros((0, 2)), radii=0.04, colors=colours,
                                                 labels=labels, show_labels=False), recording=rec)
        present = set()
        for row in rows:
            key = f"{row.cls}_{row.track_id}"
            present.add(key)
            trail = self._trails.setdefault(key, collections.deque(maxlen=TRAIL))
            trail.append((row.x, row.y))
            c = _colour(row.track_id)
            rr.log(f"field/tracks/{key}/pose", rr.Arrows2D(
                origins=[(row.x, row.y)], vectors=[(0.25 * math.cos(row.theta), 0.25 * math.sin(row.theta))],
                colors=[c], radii=0.015, labels=[_track_label(row)]), recording=rec)
            rr.log(f"field/tracks/{key}/ellipse", rr.LineStrips2D(
                [ellipse(row.x, row.y, row.var_x, row.var_y, cov_xy=row.cov_xy)], colors=[c], radii=0.005), recording=rec)
            rr.log(f"field/tracks/{key}/trail", rr.LineStrips2D([list(trail)], colors=[c], radii=0.006), recording=rec)
        for key in [k for k in self._trails if k not in present]:  # a track that ended (or is not reported)
            rr.log(f"field/tracks/{key}", rr.Clear(recursive=True), recording=rec)
            del self._trails[key]
        rr.log("stats/tracks", rr.Scalars(float(len(rows))), recording=rec)
        if err_cm.size:
            rr.log(f"stats/landmark_residual_cm{suffix}", rr.Scalars(float(err_cm.max())), recording=rec)
        if latency_ms is not None:
            rr.log("stats/latency_ms", rr.Scalars(float(latency_ms)), recording=rec)
        if dropped is not None:
            rr.log(f"stats/dropped{suffix}", rr.Scalars(float(dropped)), recording=rec)



def open_recording(name: str, mode: str | None, save: Path | None, blueprint, *, web_port: int | None = None,
                   grpc_port: int | None = None, host: str | None = None):
    """A Rerun recording with the sinks ``mode`` and ``save`` ask for (see :class:`View`): ``(recording,
    the web page's address or None, the web server's process or None)``."""
    rr = _rr()
    if mode not in (None, "native", "web"):
        raise InputError("--view", f"{mode!r}: give --view (the native viewer) or --view web")
    rec = rr.RecordingStream(name)
    url = server = None
    sinks = [rr.FileSink(str(save))] if save is not None else []
    if mode == "web":  # Rerun's gRPC proxy buffers the recording; the web viewer's page connects to it
        host = host or os.environ.get("GTSJAX_VIEW_HOST") or WEB_HOST
        grpc_port = grpc_port or int(os.environ.get("GTSJAX_VIEW_GRPC_PORT", "9876"))
        port = web_port or int(os.environ.get("GTSJAX_VIEW_WEB_PORT", "9090"))
        server = serve_web(host, port, grpc_port)
        local = "127.0.0.1" if host in ("0.0.0.0", "::") else _url_host(host)
        sinks.append(rr.GrpcSink(url=f"rerun+http://{local}:{grpc_port}/proxy"))
        there = _url_host(host)
        url = f"http://{there}:{port}/?url=rerun+http://{there}:{grpc_port}/proxy"
    elif mode == "native":
        if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            raise InputError("--view", "no display to open Rerun's viewer on: --view web serves it to a browser, "
                                       "--view-save FILE.rrd records it")
        # The viewer's executable comes with the wheel, beside this Python (a venv's bin/, which need
        # not be on PATH when gtsjax is run by its full path).
        here = os.path.dirname(sys.executable)
        if here not in os.environ.get("PATH", "").split(os.pathsep):
            os.environ["PATH"] = here + os.pathsep + os.environ.get("PATH", "")
        try:
            rec.spawn(connect=False)
        except RuntimeError as err:
            raise InputError("--view", f"could not start Rerun's viewer ({str(err).splitlines()[0]}); "
                                       "--view web serves it to a browser instead") from None
        sinks.append(rr.GrpcSink())
    if sinks:
        rec.set_sinks(*sinks, default_blueprint=blueprint)
    return rec, url, server


def grade_view(grades, site, t0: float, *, mode: str | None = None, save: Path | None = None):
    """A grade in Rerun (``gtsjax grade --view``): the field with each robot's ground-truth path and its
    belief's (at its clock offset, in the field's frame), both poses at each row on the timeline, and
    each robot's position and heading error over time. Returns the :class:`Recording`, to close."""
    import rerun.blueprint as rrb

    rr = _rr()
    field = rrb.Spatial2DView(origin="/", contents="/field/**", name="field (O), y up")
    series = [rrb.TimeSeriesView(origin=f"errors/{kind}", name=title) for kind, title in (
        ("position_cm", "position error [cm]"), ("heading_deg", "|heading error| [°]"))]
    out = Recording()
    out.rec, out.url, out.server = open_recording("gtsjax grade", mode, save, rrb.Blueprint(
        rrb.Horizontal(field, rrb.Vertical(*series), column_shares=[3, 1]), collapse_panels=True))
    rec = out.rec
    rr.log("field", rr.Transform3D(mat3x3=Y_UP), static=True, recording=rec)
    if site is not None:
        if site.bounds is not None:
            x0, y0, x1, y1 = site.bounds
            rr.log("field/bounds", rr.LineStrips2D([[(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)]],
                                                   colors=[(200, 200, 200)], radii=0.01), static=True, recording=rec)
        xy = site.landmark_xy
        rr.log("field/landmarks", rr.Points2D(xy, radii=0.06, colors=[(110, 110, 110)],
                                              labels=[lm.cls for lm in site.landmarks]), static=True, recording=rec)
    for k, g in enumerate(grades):
        e = g.errors
        if e.t.size == 0:
            continue
        part = rr.escape_entity_path_part(g.name)
        colour = _COLOURS[k % len(_COLOURS)]
        rr.log(f"field/robots/{part}/truth_path", rr.LineStrips2D([e.truth[:, :2]], colors=[(150, 150, 150)],
                                                                  radii=0.02), static=True, recording=rec)
        rr.log(f"field/robots/{part}/belief_path", rr.LineStrips2D([e.belief[:, :2]], colors=[colour], radii=0.006),
               static=True, recording=rec)
        times = [rr.TimeColumn("stamp", timestamp=e.t)]
        ones = [1] * e.t.size
        for what, poses, c, r in (("truth", e.truth, (90, 90, 90), 0.05), ("belief", e.belief, colour, 0.035)):
            rr.send_columns(f"field/robots/{part}/{what}", indexes=times, columns=rr.Arrows2D.columns(
                origins=poses[:, :2], vectors=0.25 * np.stack([np.cos(poses[:, 2]), np.sin(poses[:, 2])], -1),
                colors=[c] * e.t.size, radii=[r / 5] * e.t.size,
                labels=[g.name if what == "belief" else ""] * e.t.size).partition(ones), recording=rec)
        rr.send_columns(f"errors/position_cm/{part}", indexes=times,
                        columns=rr.Scalars.columns(scalars=100.0 * e.pos), recording=rec)
        rr.send_columns(f"errors/heading_deg/{part}", indexes=times,
                        columns=rr.Scalars.columns(scalars=np.degrees(np.abs(e.head))), recording=rec)
    return out
