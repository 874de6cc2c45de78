"""The renderer node: the latest avatar snapshot, rendered for whoever asks, on avatar/image.

- Snapshots (avatar/snapshot, latched) are turned into a renderer in a background thread and
  swapped in by reference between two renders: rendering never waits for a load, and a newer
  snapshot arriving during a load replaces the one queued. A snapshot that fails to load is
  counted and the previous one stays. When the trainer dies the last snapshot keeps serving.
- ViewRequests (avatar/view): ``follow_live`` ones are standing views (one per requesting
  source, the latest request replacing the previous), rendered with every new body/pose;
  the others are one-shot renders of the pose they carry, served first. Each standing view
  and default view is a stream whose colours are recomputed in turns (``color_refresh``;
  stg_node/avatar/color_cache.py); one-shot renders are exact.
- With no standing view, the default views (``default_view``): the training camera (from
  camera/frame) and/or an orbit around the body, alternating when both.
- Renders at most ``max_rate_hz`` on average (on a new pose; a token bucket, pacing.py, so poses
  arriving at that rate with some jitter are all rendered), at least ``idle_rate_hz`` (last pose again).
- Each RenderedImage carries the pose's / request's seq and stamp, the snapshot version,
  ``render_ms`` and ``latency_ms`` (source stamp to publication).
- ``record_dir``: default-view images are written there; an MP4 and a contact sheet at the end.
- Acknowledgements (the runtime's ``ack``, for lockstep replay): a one-shot avatar/view once its
  image is published; a standing view, a pose or a frame when taken in; a snapshot once the
  loader is done with it (swapped in, refused, or replaced by a newer one).

All calls into the avatar package go through :mod:`.avatar_adapter`.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np

from stg_node.bus import BodyPose, Frame, GaussianSnapshot, RenderedImage, ViewRequest
from stg_node.data.types import Camera, SmplParams
from stg_node.nodes.avatar_adapter import DEFAULT_MODULE, RendererAdapter, avatar_module
from stg_node.nodes.convert import frame_camera, request_camera, request_smpl, resized_camera
from stg_node.nodes.pacing import Pacer
from stg_node.nodes.params import param
from stg_node.nodes.runtime import Node
from stg_node.nodes.views import FramedOrbit, default_camera, orbit_camera


@dataclass
class RendererParams:
    avatar: str = param(DEFAULT_MODULE, doc="package implementing the avatar API (tests: a fake)")
    device: str = param("cpu", doc="torch device")
    backend: str = param("auto", doc="rasterizer backend: auto (the best available), cpu, cuda, torch")
    light: str = param(
        "learned",
        doc="light of an avatar with shading: learned (fixed in the world), baked (turns with the body), "
        "albedo, 27 comma-separated SH numbers, or a JSON file (docs/AVATAR.md)",
    )
    size: int = param(256, min=8, max=4096, unit="px", doc="default views: longer side")
    default_view: Literal["train", "orbit", "both", "none"] = param(
        "both", doc="what to render when nobody asks"
    )
    orbit_period_s: float = param(8.0, min=0.1, unit="s", doc="one turn of the orbit view")
    max_rate_hz: float = param(
        30.0,
        min=0.1,
        unit="Hz",
        doc="renders per second at most, on average (standing views; 2 at once absorb jitter)",
    )
    idle_rate_hz: float = param(
        2.0, min=0.0, unit="Hz", doc="re-render the last pose this often (0: only on new poses)"
    )
    view_ttl_s: float = param(
        0.0, min=0.0, unit="s", doc="forget a standing view not renewed for this long (0: never)"
    )
    max_oneshot: int = param(64, min=1, doc="one-shot requests queued at most (the oldest are dropped)")
    color_refresh: int = param(
        2,
        min=1,
        max=16,
        doc="live views: recompute each Gaussian's colour every Nth frame, in turns (1: every frame; "
        "one-shot requests and renders on a GPU are always exact)",
    )
    record_dir: str = param("", doc="write default-view images here, and an MP4 + contact sheet at the end")
    record_every: int = param(1, min=1, doc="record every Nth default-view image")
    video_fps: float = param(15.0, min=1.0, unit="Hz", doc="frame rate of the recorded MP4")
    drain_s: float = param(
        0.5, min=0.0, unit="s", doc="on stop: wait this long for a last snapshot to render"
    )


class SnapshotLoader:
    """Builds renderers from snapshots in a background thread; the newest finished one wins."""

    def __init__(self, build, on_error):
        self._build = build
        self._on_error = on_error
        self._pending: GaussianSnapshot | None = None
        self._ready: RendererAdapter | None = None
        self._cond = threading.Condition()
        self._closed = False
        self.loading = False
        self._thread = threading.Thread(target=self._run, name="snapshot-loader", daemon=True)
        self._thread.start()

    def submit(self, msg: GaussianSnapshot) -> None:
        with self._cond:
            self._pending = msg  # a newer snapshot replaces one not yet started
            self._cond.notify()

    def take(self) -> RendererAdapter | None:
        """The newest renderer finished since the last call, or None."""
        with self._cond:
            ready, self._ready = self._ready, None
            return ready

    @property
    def busy(self) -> bool:
        with self._cond:
            return self.loading or self._pending is not None

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                msg, self._pending = self._pending, None
                self.loading = True
            try:
                built = self._build(msg)
            except Exception as exc:  # a bad snapshot must not take the renderer down
                self._on_error(msg, exc)
                built = None
            with self._cond:
                self.loading = False
                if built is not None and (self._ready is None or built.version >= self._ready.version):
                    self._ready = built

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(timeout=10.0)


@dataclass
class StandingView:
    request: ViewRequest
    renewed: float  # time.monotonic()


class RendererNode(Node):
    """Renders avatar/image for avatar/view requests, or default views."""

    kind = "renderer"
    Params = RendererParams

    @classmethod
    def prepare(cls, params: RendererParams) -> None:
        from stg_node.threads import configure_threads

        configure_threads()
        avatar_module(params.avatar)  # torch and the avatar package
        if params.device == "cpu" and params.backend in ("auto", "cpu"):
            from stg_node.splat.build import load_kernels

            load_kernels()  # the rasterizer's compiled kernels (built once, cached)

    def setup(self) -> None:
        from stg_node.threads import configure_threads

        configure_threads()
        p = self.params
        if p.light != "learned":
            from stg_node.avatar.shading import parse_light

            parse_light(p.light)  # a bad light stops the node at start, with the reason
        self.current: RendererAdapter | None = None
        self.loader = SnapshotLoader(self._build, self._load_failed)
        self.pose: BodyPose | None = None
        self.new_pose = False
        self.train_camera: Camera | None = None
        self.standing: dict[str, StandingView] = {}
        self.oneshots: deque[ViewRequest] = deque()
        self.last_render = 0.0
        self.pacer = Pacer(p.max_rate_hz, now=time.monotonic())  # the cap on new poses (pacing.py)
        self.default_turn = 0
        self.framed_orbit = FramedOrbit()
        self.started = time.monotonic()
        self.published = 0
        self.swaps = 0
        self.recorder = None
        if p.record_dir:
            from stg_node.nodes.recording import ImageRecorder

            self.recorder = ImageRecorder(p.record_dir, every=p.record_every, fps=p.video_fps)
        self.snapshots = self.subscribe("avatar/snapshot")
        self.poses = self.subscribe("body/pose", keep_last=True)  # only the newest pose matters
        self.views = self.subscribe("avatar/view")
        self.frames = self.subscribe("camera/frame")  # keep-last: the training camera
        self._waiting_logged = False
        self.loading_snapshots: list[GaussianSnapshot] = []  # acknowledged when the loader is idle

    # -- snapshots ---------------------------------------------------------------------------------------

    def _build(self, msg: GaussianSnapshot) -> RendererAdapter:
        p = self.params
        return RendererAdapter.from_snapshot(
            msg,
            module=p.avatar,
            device=p.device,
            backend=p.backend,
            color_refresh_every=p.color_refresh,
            light=p.light,
        )

    def _load_failed(self, msg: GaussianSnapshot, exc: Exception) -> None:
        self.drop("bad_snapshot")
        self.error(f"snapshot v{msg.model_version} not loaded: {exc}")
        self.log.warning(
            "snapshot v%d (%s) not loaded, keeping the previous one: %s", msg.model_version, msg.format, exc
        )

    def _swap(self) -> None:
        idle = not self.loader.busy  # before take(): then every snapshot loaded is in what it returns
        built = self.loader.take()
        if built is not None and (self.current is None or built.version >= self.current.version):
            self.current = built
            self.swaps += 1
            self.log.info("rendering snapshot v%d", built.version)
        if self.loading_snapshots and idle:
            for msg in self.loading_snapshots:
                self.acknowledge(msg)
            self.loading_snapshots.clear()

    # -- input --------------------------------------------------------------------------------------------

    def _take_input(self) -> None:
        while (msg := self.snapshots.recv(timeout=0)) is not None:
            if self.current is None or msg.model_version >= self.current.version:
                self.loader.submit(msg)
                self.loading_snapshots.append(msg)
            else:
                self.acknowledge(msg)
        msg = self.poses.recv(timeout=0)
        if msg is not None:
            self.pose, self.new_pose = msg, True
            self.acknowledge(msg)
        frame: Frame | None = self.frames.recv(timeout=0)
        if frame is not None:
            self.train_camera = frame_camera(frame)
            self.acknowledge(frame)
        now = time.monotonic()
        for _ in range(256):
            req = self.views.recv(timeout=0)
            if req is None:
                break
            if req.follow_live:
                self.standing[req.header.src] = StandingView(req, now)
                self.acknowledge(req)
            else:
                if len(self.oneshots) >= self.params.max_oneshot:
                    self.acknowledge(self.oneshots.popleft())  # dropped: nothing more will come of it
                    self.drop("oneshot_overflow")
                self.oneshots.append(req)
        ttl = self.params.view_ttl_s
        if ttl:
            for src in [s for s, v in self.standing.items() if now - v.renewed > ttl]:
                del self.standing[src]

    # -- rendering --------------------------------------------------------------------------------------

    def _publish(
        self,
        camera: Camera,
        smpl: SmplParams,
        *,
        time_s: float | None,
        source_stamp_ns: int,
        pose_seq: int,
        request: ViewRequest | None,
        record_label: str = "",
        stream: str | None = None,
    ) -> None:
        out = self.current.render(camera, smpl, time=time_s, stream=stream)
        image = RenderedImage(
            request_id=request.request_id if request is not None else -1,
            request_src=request.header.src if request is not None else "",
            pose_seq=pose_seq,
            snapshot_version=self.current.version,
            source_stamp_ns=max(0, int(source_stamp_ns)),
            render_ms=max(0.0, out.render_ms),
            image=out.image,
            alpha=out.alpha,
            K=np.asarray(camera.K, np.float64),
            R=np.asarray(camera.R, np.float64),
            t=np.asarray(camera.t, np.float64),
        )
        image.latency_ms = (time.time_ns() - image.source_stamp_ns) / 1e6 if source_stamp_ns else 0.0
        self.publish(image)
        self.published += 1
        if self.recorder is not None and record_label:
            self.recorder.add(out.image, record_label)

    def _render_oneshot(self, req: ViewRequest) -> None:
        betas = self.pose.betas if self.pose is not None else None
        self._publish(
            request_camera(req),
            request_smpl(req, betas),
            time_s=req.time if req.time >= 0 else None,
            source_stamp_ns=req.header.stamp_ns,
            pose_seq=-1,
            request=req,
        )

    def _default_cameras(self) -> list[tuple[Camera, str]]:
        view = self.params.default_view
        if view == "none":
            return []
        train = self.train_camera or default_camera()
        train = resized_camera(train, self.params.size)
        choices = []
        if view in ("train", "both"):
            choices.append((train, "train"))
        if view in ("orbit", "both"):
            now = time.monotonic()
            angle = 2 * math.pi * ((now - self.started) / self.params.orbit_period_s % 1.0)
            choices.append((self._orbit_camera(train, angle, now), f"orbit {math.degrees(angle):.0f}"))
        if view == "both":
            self.default_turn += 1
            return [choices[self.default_turn % 2]]
        return choices

    def _orbit_camera(self, train: Camera, angle: float, now: float) -> Camera:
        """The orbit view framed on the live body (stg-render's rule), or, when the avatar cannot
        say where its body is, circling the body's root at the training camera's distance."""
        points = None
        if self.pose is not None and self.current is not None:
            points = self.current.posed_points(self.pose.to_smpl(), self.pose.time)
        if points is not None:
            return self.framed_orbit.camera(points, train, angle, now)
        center = np.asarray(self.pose.Th, np.float64) if self.pose is not None else np.zeros(3)
        return orbit_camera(train, center, angle)

    def _final_views(self, orbit_views: int = 11) -> list[tuple[np.ndarray, str]] | None:
        """The last snapshot on the last pose, from the training camera and ``orbit_views`` angles of
        the framed orbit: the contact sheet of the recording shows the trained avatar."""
        if self.current is None or self.pose is None:
            return None
        smpl = self.pose.to_smpl()
        train = resized_camera(self.train_camera or default_camera(), self.params.size)
        version = self.current.version
        views = [(self.current.render(train, smpl, time=self.pose.time).image, f"v{version} training camera")]
        points = self.current.posed_points(smpl, self.pose.time)
        for k in range(orbit_views):
            angle = 2 * math.pi * k / orbit_views
            orbit = FramedOrbit()  # no smoothing history: each angle framed on its own
            camera = (
                orbit.camera(points, train, angle, 0.0)
                if points is not None
                else orbit_camera(train, np.asarray(self.pose.Th, np.float64), angle)
            )
            image = self.current.render(camera, smpl, time=self.pose.time).image
            views.append((image, f"v{version} orbit {math.degrees(angle):.0f}"))
        return views

    def _render_live(self) -> None:
        pose = self.pose
        smpl = pose.to_smpl()
        common = {"time_s": pose.time, "source_stamp_ns": pose.header.stamp_ns, "pose_seq": pose.header.seq}
        if self.standing:
            for src, view in list(self.standing.items()):
                req = view.request
                self._publish(request_camera(req), smpl, request=req, stream=f"view:{src}", **common)
        else:
            for camera, label in self._default_cameras():
                stream = "default:" + label.split()[0]  # "train", or "orbit" (its angle moves on)
                self._publish(camera, smpl, request=None, record_label=label, stream=stream, **common)

    def _due(self, now: float) -> bool:
        p = self.params
        if self.new_pose and self.pacer.ready(now):
            return True
        return p.idle_rate_hz > 0 and now - self.last_render >= 1.0 / p.idle_rate_hz

    def _round(self) -> bool:
        """One round: input, swap, renders due. True if anything was rendered."""
        self._take_input()
        self._swap()
        if self.current is None:
            if not self._waiting_logged:
                self.log.info("waiting for a snapshot on avatar/snapshot")
                self._waiting_logged = True
            return False
        rendered = False
        while self.oneshots and not self.stopping:
            request = self.oneshots.popleft()
            self._render_oneshot(request)
            self.acknowledge(request)
            rendered = True
        now = time.monotonic()
        if self.pose is not None and self._due(now):
            if self.new_pose:
                self.pacer.take(now)
            self._render_live()
            self.new_pose = False
            self.last_render = now
            rendered = True
        return rendered

    def run(self) -> None:
        while not self.stopping:
            if not self._round():
                wait = 0.01 if self.loader.busy else 0.05
                if self.new_pose and self.current is not None:  # a pose waits for the rate cap: no longer
                    wait = min(wait, self.pacer.wait_s(time.monotonic()))
                self.wait_for_messages(wait)

    def teardown(self) -> None:
        loader = getattr(self, "loader", None)
        if loader is None:
            return
        deadline = time.monotonic() + self.params.drain_s
        final = self.current.version if self.current is not None else -1
        while time.monotonic() < deadline:  # a last snapshot published just before the stop
            self._take_input()
            self._swap()
            if not loader.busy:
                if self.current is not None and self.current.version != final:
                    break
                time.sleep(0.02)
        if self.current is not None and self.current.version != final and self.pose is not None:
            self.last_render = 0.0
            self._render_live()
        loader.close()
        if self.recorder is not None:
            written = self.recorder.finish(sheet=self._final_views())
            for what, path in written.items():
                self.log.info("wrote %s %s", what, path)
        self.log.info("published %d images, %d snapshot swaps", self.published, self.swaps)
