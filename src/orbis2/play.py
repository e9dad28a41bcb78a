"""``orbis2 play``: drive the world model live in the browser.

A small ASGI app (Starlette on uvicorn) serves one self-contained page (``play.html``: no script, font or
style from anywhere else, and a Content-Security-Policy that forbids them) and a websocket. The page pulls
one 0.5 s step at a time with its current command, so the server generates only what is about to be shown,
idles while the page is paused, hidden or closed, and a key press reaches the picture within about one step
plus its generation time. Frames travel as JPEG. The models are loaded and one step is generated before the
server listens, so the first key press does not wait for a warm-up.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import os
import socket
import time
from importlib.resources import files
from pathlib import Path

import cv2
import numpy as np
import torch
import uvicorn
from starlette.applications import Starlette
from starlette.responses import FileResponse, HTMLResponse, JSONResponse, Response
from starlette.routing import Route, WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect

from orbis2.drive import Drive, Models, Scene, find_scenes, load_models
from orbis2.errors import OrbisError

# Only this server, inline scripts and styles, and images it sends as data: URLs.
CSP = ("default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; img-src 'self' data:; "
       "connect-src 'self'; base-uri 'none'; form-action 'none'")
MAX_SPEED = 20.0  # m/s the page lets you reach (72 km/h, above every town clip's speed)
MAX_YAW_RATE = 0.5  # rad/s a held turn key reaches (a town corner is about 0.35)


def jpeg(frame: np.ndarray, quality: int = 90) -> str:
    """An RGB frame as base64 JPEG."""
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(frame, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    return base64.b64encode(data.tobytes()).decode("ascii")


class Player:
    """The server's state: the models, the scenes, one lock so that steps of several tabs do not interleave, and
    a count of generated steps (``/status``: a closed tab must stop it)."""

    def __init__(self, models: Models, scenes: list[Scene], seed: int, record_dir: Path):
        self.models, self.scenes, self.seed, self.record_dir = models, scenes, seed, record_dir
        self.lock = asyncio.Lock()
        self.steps_generated = 0
        self.clients = 0

    def warm_up(self) -> float:
        """Generate steps from the first scene and drop them: allocations, caches and any compile happen now (two
        steps; compiled, a whole abstract window, after which no new shape comes)."""
        started = time.perf_counter()
        drive = Drive(self.models, self.scenes[0], self.seed)
        for _ in range(self.models.cfg.data.abstract_window + 1 if self.models.args.compile else 2):
            drive.step(float(drive.speed[-1]), 0.0)
        return time.perf_counter() - started

    def hello(self) -> dict:
        data = self.models.cfg.data
        return {"type": "hello", "fps": data.detail_hz, "step_seconds": 1 / data.abstract_hz,
                "max_speed": MAX_SPEED, "max_yaw_rate": MAX_YAW_RATE, "width": data.width, "height": data.height,
                "scenes": [{"id": i, "name": s.name} for i, s in enumerate(self.scenes)]}

    async def session(self, ws: WebSocket) -> None:
        """One page: start a scene, then a step per request, until the page goes."""
        drive: Drive | None = None
        await ws.send_json(self.hello())
        while True:
            message = await ws.receive_json()
            kind = message.get("type")
            try:
                if kind == "start":
                    scene = self.scenes[int(message["scene"])]
                    async with self.lock:
                        drive = await asyncio.to_thread(Drive, self.models, scene, self.seed)
                    await ws.send_json({"type": "started", "scene": scene.name, "frame": jpeg(drive.context_frames[-1]),
                                        "speed": float(drive.speed[-1]), "true_view": drive.truth is not None})
                elif kind == "step" and drive is not None:
                    async with self.lock:
                        started = time.perf_counter()
                        frames = await asyncio.to_thread(drive.step, float(message["speed"]),
                                                         float(message["yaw_rate"]), bool(message.get("replay")),
                                                         bool(message.get("forecast")),
                                                         bool(message.get("true_view", True)))
                        seconds = time.perf_counter() - started
                        self.steps_generated += 1
                    x, y = drive.path()
                    chunk = {"type": "chunk", "step": drive.steps, "seconds": seconds,
                             "frames": [jpeg(f) for f in frames.generated], "request": message.get("request"),
                             "speed": float(drive.speed[-1]), "yaw_rate": float(drive.yaw_rate[-1]),
                             "path": np.stack([x, y], 1)[:: max(1, len(x) // 400)].round(3).tolist()}
                    if frames.forecast is not None:
                        chunk["forecast"] = jpeg(frames.forecast)
                    if frames.true is not None:
                        true = frames.true
                        chunk |= {"true_frames": [jpeg(f) for f in true.rgb], "psnr": frames.psnr,
                                  "true_heading": float(true.yaw[-1] - drive.truth.recorded.yaw[drive.context_end]),
                                  "collision": bool(true.collision.any()), "off_road": bool(true.off_road.any())}
                    await ws.send_json(chunk)
                elif kind == "save" and drive is not None:
                    stamp = time.strftime("%Y%m%d-%H%M%S")
                    out = self.record_dir / f"play-{drive.scene.name}-{stamp}.mp4"
                    video, gif, trajectory = await asyncio.to_thread(drive.save, out)
                    replay = drive.replay_command(out.with_name(out.stem + "-replay.mp4"), trajectory)
                    await ws.send_json({"type": "saved", "files": [p.name for p in (video, gif, trajectory)],
                                        "paths": [str(p) for p in (video, gif, trajectory)],
                                        "replay": " ".join(replay)})
            except OrbisError as err:
                await ws.send_json({"type": "error", "message": str(err)})


def build_app(player: Player) -> Starlette:
    page = files("orbis2").joinpath("play.html").read_text(encoding="utf-8")

    async def index(request) -> HTMLResponse:
        return HTMLResponse(page, headers={"Content-Security-Policy": CSP, "Cache-Control": "no-store"})

    async def thumbnail(request) -> Response:
        index = int(request.path_params["index"])
        if not 0 <= index < len(player.scenes):
            return Response(status_code=404)
        drive_frames = await asyncio.to_thread(first_frame, player.scenes[index])
        return Response(base64.b64decode(jpeg(drive_frames, 80)), media_type="image/jpeg")

    async def recording(request) -> Response:
        path = player.record_dir / request.path_params["name"]
        if path.parent != player.record_dir or not path.is_file():
            return Response(status_code=404)
        return FileResponse(path)

    async def status(request) -> JSONResponse:
        return JSONResponse({"steps_generated": player.steps_generated, "clients": player.clients})

    async def websocket(ws: WebSocket) -> None:
        await ws.accept()
        player.clients += 1
        try:
            await player.session(ws)
        except WebSocketDisconnect:
            pass
        finally:
            player.clients -= 1

    return Starlette(routes=[Route("/", index), Route("/thumb/{index:int}.jpg", thumbnail),
                             Route("/recordings/{name}", recording), Route("/status", status),
                             WebSocketRoute("/ws", websocket)])


def first_frame(scene: Scene) -> np.ndarray:
    """A scene's first frame, for its thumbnail."""
    capture = cv2.VideoCapture(str(scene.video))
    ok, frame = capture.read()
    capture.release()
    if not ok:
        raise OrbisError(f"{scene.video}: cannot read a frame")
    return cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)


def bind(host: str, port: int) -> socket.socket:
    """The listening socket, taken before the models load, so that a busy port fails at once."""
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
    try:
        sock.bind((host, port))
    except OSError as err:
        sock.close()
        raise OrbisError(f"{host}:{port}: cannot listen ({err.strerror}); pass another --port "
                         f"(0 picks a free one)") from err
    sock.listen(16)
    return sock


def cpu_threads() -> int:
    """Torch's threads on the CPU: the cores this process may use less one, left to the browser, the true view's
    renderer and the server (batch-1 sampling gains little from a second thread; a busy core slows it a lot)."""
    return max(1, len(os.sched_getaffinity(0)) - 1)


def play_command(args: argparse.Namespace) -> str:
    sock = bind(args.host, args.port)
    scenes = find_scenes(args.video)
    models = load_models(args)
    threads = ""
    if models.device.type == "cpu":
        torch.set_num_threads(args.threads or cpu_threads())
        threads = f"; {torch.get_num_threads()} torch threads"
    player = Player(models, scenes, args.seed, args.record_dir.resolve())
    print(f"orbis2 play: {models.summary}{threads}", flush=True)
    print(f"orbis2 play: {len(scenes)} scenes; warming up ...", flush=True)
    seconds = player.warm_up()
    host, port = sock.getsockname()[:2]
    print(f"orbis2 play: warmed up in {seconds:.1f} s; ready at http://{host}:{port}/ (Ctrl-C to stop)", flush=True)
    server = uvicorn.Server(uvicorn.Config(build_app(player), log_level="warning", ws="wsproto"))
    server.run(sockets=[sock])
    return f"orbis2 play: stopped after {player.steps_generated} steps"
