#!/usr/bin/env python3
"""Fuzz every file a user hands stg_node: each broken file must give a clear one-line error that
names the file, and exit code 1 or 2: never a traceback, a hang or a crash.

    python tools/fuzz_inputs.py [--cases 40] [--formats launch,poses,...] [--seed 0] [--json out.json]

Formats, each fed to the command a user would run on it (in a worker process that imports once):

| format | seed files | command |
|---|---|---|
| launch | the shipped launch files | ``stg-launch --validate FILE ARGS`` |
| poses | a POSES.npz as ``stg-track`` writes it | ``stg-render RUN --poses FILE`` (a tiny trained run) |
| zju | a ZJU-MoCap subject (original layout) | ``stg-train --data DIR --format zju --iters 1`` |
| thuman4 | a THuman4.0 subject | ``stg-train --data DIR --format thuman4 --iters 1`` |
| folder | a folder-format capture | ``stg-train --data DIR --format folder --iters 1`` |
| smpl | SMPL-format model files (.npz and .pkl) | ``stg-synth --body FILE`` (one small frame) |
| mcap | a recording of every message type | ``stg-bag info FILE`` and ``stg-bag export FILE`` |
| intrinsics | an intrinsics JSON for a video | ``stg-track VIDEO --intrinsics FILE`` |
| rig | a rig.json of two cameras (stg-calibrate's output) | ``stg-track VIDEO VIDEO --calibration FILE`` |

Each case copies a valid seed and damages one file of it: truncated (at several places, to 0
bytes), bytes flipped or replaced, arrays and keys removed, NaN and infinity, wrong dtypes and
shapes, huge dimensions (an array header that promises terabytes), wrong types in JSON/YAML,
YAML alias bombs, and random combinations of these (``--cases`` random ones per format on top of
the fixed list, from ``--seed``). A case fails when the command crashed (a signal), hung (past
``--timeout``), printed a traceback, exited with anything but 0, 1 or 2, or failed without a
line that names the damaged file. A damaged file the command accepts (exit 0) is counted, not
failed: not every change makes a file invalid. The worker runs with a 4 GB address-space limit,
so a file that makes it allocate without bound fails the case (MemoryError) instead of the machine.
Exit code 0 when no case failed, 1 otherwise. Figures: docs/SECURITY.md.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

FORMATS = ("launch", "poses", "zju", "thuman4", "folder", "smpl", "mcap", "intrinsics", "rig")
WORKER_MEMORY = 4 << 30
ENTRIES = {
    "stg-launch": "stg_node.cli.launch",
    "stg-render": "stg_node.cli.render",
    "stg-train": "stg_node.cli.train",
    "stg-synth": "stg_node.cli.synth",
    "stg-bag": "stg_node.cli.bag",
    "stg-track": "stg_node.cli.track",
    "stg-node": "stg_node.cli.node",
}


# --- the worker: runs commands in-process, one per request ------------------------------------------


def worker() -> int:
    """Read JSON requests on stdin, run ``ENTRIES[cmd].main(argv)`` with its output captured, answer
    on stdout. The parent restarts the worker when a case kills or hangs it."""
    import importlib
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (WORKER_MEMORY, WORKER_MEMORY))
    answers = os.fdopen(os.dup(1), "w")
    sys.stdout = sys.stderr = io.StringIO()
    for line in sys.stdin:
        request = json.loads(line)
        out = io.StringIO()
        start = time.monotonic()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            try:
                module = importlib.import_module(ENTRIES[request["cmd"]])
                code = module.main(request["argv"])
            except SystemExit as exc:  # argparse
                code = exc.code if isinstance(exc.code, int) else 2
            except BaseException as exc:  # a command must never let one out; say what it was
                import traceback

                traceback.print_exc(file=out)
                code = f"raised {type(exc).__name__}"
        answers.write(
            json.dumps({"code": code, "output": out.getvalue()[-6000:], "s": time.monotonic() - start})
        )
        answers.write("\n")
        answers.flush()
    return 0


class Worker:
    """The parent's handle on a worker process."""

    def __init__(self, env: dict[str, str]):
        self.env = env
        self.proc: subprocess.Popen | None = None

    def _start(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "--worker"],
            cwd=ROOT, env=self.env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL, text=True, start_new_session=True,
        )  # fmt: skip

    def run(self, cmd: str, argv: list[str], timeout: float) -> dict:
        if self.proc is None or self.proc.poll() is not None:
            self._start()
        self.proc.stdin.write(json.dumps({"cmd": cmd, "argv": argv}) + "\n")
        self.proc.stdin.flush()
        import selectors

        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        ready = sel.select(timeout)
        sel.close()
        if not ready:
            self.kill()
            return {"code": "hang", "output": f"no answer within {timeout:g} s", "s": timeout}
        line = self.proc.stdout.readline()
        if not line:
            code = self.proc.wait()
            self.proc = None
            return {
                "code": f"crash (signal {-code})" if code < 0 else f"worker exit {code}",
                "output": "",
                "s": 0,
            }
        return json.loads(line)

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()
            self.proc = None


# --- seeds: valid inputs of every format ---------------------------------------------------------------


def run_cli(cmd: str, argv: list[str], env: dict[str, str]) -> None:
    module = ENTRIES[cmd]
    result = subprocess.run(
        [sys.executable, "-m", module, *argv], cwd=ROOT, env=env, capture_output=True, text=True
    )
    if result.returncode != 0:
        raise SystemExit(
            f"fuzz: building a seed with {cmd} {' '.join(argv)} failed:\n{result.stdout}{result.stderr}"
        )


def build_seeds(seeds: Path, formats: set[str], env: dict[str, str]) -> dict[str, Path]:
    """Valid inputs, built once in ``seeds`` (kept between runs)."""
    from tests.fixtures.datasets import write_folder, write_thuman4, write_zju_original

    seeds.mkdir(parents=True, exist_ok=True)
    out: dict[str, Path] = {}
    if formats & {"zju", "poses"}:
        out["zju"] = seeds / "zju"
        if not out["zju"].exists():
            write_zju_original(out["zju"], num_frames=3, num_cams=1)
    if "thuman4" in formats:
        out["thuman4"] = seeds / "thuman4"
        if not out["thuman4"].exists():
            write_thuman4(out["thuman4"], num_frames=3, num_cams=1)
    if "folder" in formats:
        out["folder"] = seeds / "folder"
        if not out["folder"].exists():
            write_folder(out["folder"], num_frames=3, num_cams=1)
    if "smpl" in formats:
        from tests.smpl_fixtures import random_smpl_arrays, write_smpl_npz, write_smpl_pkl

        arrays = random_smpl_arrays(seed=0, num_verts=300)
        out["smpl_npz"], out["smpl_pkl"] = seeds / "body.npz", seeds / "body.pkl"
        write_smpl_npz(out["smpl_npz"], arrays)
        write_smpl_pkl(out["smpl_pkl"], arrays)
    if "poses" in formats:
        run = seeds / "run"
        if not (run / "avatar.stgsnap").is_file():
            shutil.rmtree(run, ignore_errors=True)
            train = ["--data", str(out["zju"]), "--format", "zju", "--out", str(run), "--iters", "2",
                     "--preset", "fast", "--size", "32", "--no-progress"]  # fmt: skip
            run_cli("stg-train", train, env)
        out["run"] = run
        out["poses"] = seeds / "POSES.npz"
        n = 4
        rng = np.random.default_rng(0)
        np.savez(
            out["poses"],
            poses=(rng.normal(size=(n, 72)) * 0.1).astype(np.float32),
            Rh=np.zeros((n, 3), np.float32),
            Th=np.tile(np.array([0.0, 0.0, 3.0], np.float32), (n, 1)),
            shapes=np.zeros((n, 10), np.float32),
            confidence=np.ones(n, np.float32),
            frames=np.arange(n),
            times=np.arange(n) / 30.0,
            K=np.array([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]]),
            dist=np.zeros(0),
            image_size=np.array([32, 32]),
            fps=np.array(30.0),
        )
    if "mcap" in formats:
        from stg_node.bus.codec import encode
        from stg_node.bus.recording import BagWriter
        from tests.bus.bushelpers import sample_messages

        out["mcap"] = seeds / "session.mcap"
        with BagWriter(out["mcap"], chunk_size=2000) as bag:
            t = 10**18
            for k in range(3):
                for name, msg in sample_messages(k).items():
                    topic = msg.SPEC.topic if name != "Ack" else "node/ack"
                    bag.write_frames(encode(msg, topic=topic, seq=k, src="fuzz", stamp_ns=t), t)
                    t += 10**7
    if "intrinsics" in formats or "rig" in formats:
        import cv2

        out["video"] = seeds / "clip.avi"
        if not out["video"].is_file():
            writer = cv2.VideoWriter(str(out["video"]), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 64))
            for i in range(2):
                writer.write(np.full((64, 64, 3), 40 + 60 * i, np.uint8))
            writer.release()
        out["intrinsics"] = seeds / "K.json"
        out["intrinsics"].write_text(
            json.dumps({"K": [[60, 0, 32], [0, 60, 32], [0, 0, 1]], "dist": [0, 0, 0, 0]})
        )
    if "rig" in formats:  # two cameras facing each other across the origin, 2 m apart (docs/RIGS.md)
        eye, turn = [[1, 0, 0], [0, 1, 0], [0, 0, 1]], [[-1, 0, 0], [0, 1, 0], [0, 0, -1]]
        camera = {"K": [[60, 0, 32], [0, 60, 32], [0, 0, 1]], "dist": [0, 0, 0, 0, 0], "image_size": [64, 64]}
        out["rig"] = seeds / "rig.json"
        out["rig"].write_text(
            json.dumps(
                {
                    "cameras": {
                        "a": {**camera, "R": eye, "t": [0, 0, 1]},
                        "b": {**camera, "R": turn, "t": [0, 0, 1]},
                    }
                }
            )
        )
    return out


# --- damage ---------------------------------------------------------------------------------------------


def damage_bytes(path: Path, how: str, rng: random.Random) -> str:
    data = path.read_bytes()
    if how == "empty":
        path.write_bytes(b"")
    elif how == "truncate_1":
        path.write_bytes(data[:1])
    elif how.startswith("truncate_"):
        cut = int(len(data) * float(how.split("_")[1]) / 100)
        path.write_bytes(data[:cut])
    elif how == "flip":
        raw = bytearray(data)
        for _ in range(max(1, len(raw) // 200)):
            i = rng.randrange(len(raw))
            raw[i] ^= 1 << rng.randrange(8)
        path.write_bytes(bytes(raw))
    elif how == "random":
        path.write_bytes(rng.randbytes(max(len(data), 16)))
    elif how == "garbage_tail":
        path.write_bytes(data + rng.randbytes(97))
    elif how == "not_utf8":
        path.write_bytes(b"\xff\xfe\x00" + data)
    return f"{path.name}: {how}"


BYTE_DAMAGE = (
    "empty",
    "truncate_1",
    "truncate_10",
    "truncate_50",
    "truncate_90",
    "flip",
    "random",
    "garbage_tail",
)


def huge_npy_member() -> bytes:
    """An .npy whose header promises about 4 TB of float32 and holds 16 bytes."""
    header = {"descr": "<f4", "fortran_order": False, "shape": (1 << 20, 1 << 20)}
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    return buf.getvalue() + b"\0" * 16


def mutate_array(value: np.ndarray, how: str, rng: random.Random) -> np.ndarray | None:
    a = np.asarray(value)
    if how == "nan" and a.dtype.kind == "f" and a.size:
        a = a.copy()
        a.flat[rng.randrange(a.size)] = np.nan
    elif how == "inf" and a.dtype.kind == "f" and a.size:
        a = a.copy()
        a.flat[rng.randrange(a.size)] = np.inf
    elif how == "all_nan" and a.dtype.kind == "f":
        a = np.full(a.shape, np.nan, a.dtype)
    elif how == "strings":
        a = np.array(["x"] * max(1, a.size))
    elif how == "int" and a.dtype.kind in "fciub":
        a = a.astype(np.int64) if a.dtype.kind in "fc" else a.astype(np.float64)
    elif how == "complex" and a.dtype.kind in "fiu":
        a = a.astype(np.complex64)
    elif how == "drop_dim":
        a = a.reshape(-1)[: max(1, a.size // 2)]
    elif how == "extra_dim":
        a = a[..., None].repeat(2, axis=-1)
    elif how == "empty_array":
        a = np.zeros((0,) + a.shape[1:], a.dtype)
    elif how == "scalar":
        a = np.array(1.0)
    elif how == "transpose" and a.ndim >= 2:
        a = a.T.copy()
    elif how == "huge_values" and a.dtype.kind == "f":
        a = np.full(a.shape, 1e30, a.dtype)
    return a


ARRAY_DAMAGE = ("nan", "inf", "all_nan", "strings", "int", "complex", "drop_dim", "extra_dim", "empty_array",
                "scalar", "transpose", "huge_values", "missing", "huge_dims")  # fmt: skip


def damage_npz(path: Path, key: str | None, how: str, rng: random.Random) -> str:
    """Damage one member of an .npz (``key`` None: a random one)."""
    with np.load(path, allow_pickle=False) as data:
        members = {k: data[k] for k in data.files}
    key = key or rng.choice(sorted(members))
    if how == "missing":
        members.pop(key, None)
        np.savez(path, **members)
    elif how == "huge_dims":
        with zipfile.ZipFile(path, "w") as z:
            for k, v in members.items():
                buf = io.BytesIO()
                np.save(buf, v)
                z.writestr(f"{k}.npy", huge_npy_member() if k == key else buf.getvalue())
    else:
        members[key] = mutate_array(members[key], how, rng)
        np.savez(path, **members)
    return f"{path.name}[{key}]: {how}"


def damage_npy(path: Path, how: str, rng: random.Random) -> str:
    """Damage a ZJU .npy: a pickled dict of arrays (new_params, annots) or a plain array."""
    from stg_node.safe_load import load_npy

    value = load_npy(path)
    if how == "huge_dims":
        path.write_bytes(huge_npy_member())
        return f"{path.name}: huge_dims"
    if isinstance(value, dict):
        # a leaf of the nested dict (ZJU's annots: cams -> K lists, ims -> list of dicts)
        leaves = []

        def walk(node, trail):
            items = node.items() if isinstance(node, dict) else enumerate(node[:2])
            for k, v in items:
                if (
                    isinstance(v, dict | list)
                    and v
                    and not isinstance(v[0] if isinstance(v, list) else 0, int | float)
                ):
                    walk(v, (*trail, k))
                else:
                    leaves.append((*trail, k))

        walk(value, ())
        trail = rng.choice(leaves)
        parent = value
        for step in trail[:-1]:
            parent = parent[step]
        if how == "missing":
            del parent[trail[-1]]
        else:
            parent[trail[-1]] = mutate_array(np.asarray(parent[trail[-1]]), how, rng)
        np.save(path, np.array(value, dtype=object), allow_pickle=True)
        return f"{path.name}[{'.'.join(map(str, trail))}]: {how}"
    if how == "missing":
        path.unlink()
        return f"{path.name}: removed"
    np.save(path, mutate_array(value, how, rng))
    return f"{path.name}: {how}"


JSON_DAMAGE = (
    "drop_key",
    "null",
    "string",
    "nested",
    "nan",
    "huge",
    "negative",
    "wrong_list",
    "not_json",
    "list_root",
)


def damage_json(path: Path, how: str, rng: random.Random) -> str:
    doc = json.loads(path.read_text())
    paths = []

    def walk(node, trail):
        if isinstance(node, dict):
            for k, v in node.items():
                paths.append((*trail, k))
                walk(v, (*trail, k))
        elif isinstance(node, list) and node and not isinstance(node[0], (int, float)):
            for i, v in enumerate(node):
                walk(v, (*trail, i))

    walk(doc, ())
    if how == "not_json":
        path.write_text(path.read_text()[: len(path.read_text()) // 2] + "}{")
        return f"{path.name}: not JSON"
    if how == "list_root":
        path.write_text(json.dumps([doc]))
        return f"{path.name}: a list at the top"
    target = rng.choice(paths)
    parent = doc
    for step in target[:-1]:
        parent = parent[step]
    last = target[-1]
    replacement = {
        "null": None,
        "string": "x",
        "nested": {"a": [1, 2]},
        "nan": float("nan"),
        "huge": 1e308,
        "negative": -1,
        "wrong_list": [1, 2],
    }
    if how == "drop_key":
        del parent[last]
    else:
        parent[last] = replacement[how]
    path.write_text(json.dumps(doc))
    return f"{path.name}[{'.'.join(map(str, target))}]: {how}"


YAML_DAMAGE = (
    "alias_bomb", "list_for_map", "map_for_list", "wrong_types", "unknown_key", "duplicate_key", "tab_indent",
    "deep_nesting", "bad_substitution", "missing_include", "self_include", "huge_number",
)  # fmt: skip


def damage_yaml(path: Path, how: str, rng: random.Random) -> str:
    text = path.read_text()
    if how == "alias_bomb":
        bomb = ['a0: &a0 ["x", "x", "x", "x", "x", "x", "x", "x", "x"]']
        for i in range(1, 12):
            bomb.append(
                f"a{i}: &a{i} [*a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}]"
            )
        text = text + "\nbomb:\n" + "\n".join("  " + b for b in bomb) + "\n"
    elif how == "list_for_map":
        text = text.replace("params:", "params: [1, 2]\n    unused:", 1)
    elif how == "map_for_list":
        text = text.replace("nodes:", "nodes: {a: 1}\nnodes_was:", 1)
    elif how == "wrong_types":
        text = text.replace("respawn: true", "respawn: [yes, no]", 1).replace(
            "name:", "name: [x]\n    was:", 1
        )
    elif how == "unknown_key":
        text = text.replace("nodes:", "nodez: []\nnodes:", 1)
    elif how == "duplicate_key":
        text = text.replace("nodes:", "description: one\ndescription: two\nnodes:", 1)
    elif how == "tab_indent":
        text = text.replace("  ", "\t", 3)
    elif how == "deep_nesting":
        text = text + "\ndeep: " + "[" * 5000 + "]" * 5000 + "\n"
    elif how == "bad_substitution":
        text = (
            text.replace("$(arg ", "$(arg $(arg ", 1) if "$(arg " in text else text + "\nx: $(unknown thing\n"
        )
    elif how == "missing_include":
        text = text + "\ninclude:\n  - {file: /nonexistent/other.yaml}\n"
    elif how == "self_include":
        text = text + f"\ninclude:\n  - {{file: {path.name}}}\n"
    elif how == "huge_number":
        text = text.replace("respawn: true", "respawn: true\n    respawn_delay: 1e999999", 1)
    path.write_text(text)
    return f"{path.name}: {how}"


# --- cases ------------------------------------------------------------------------------------------------


@dataclass
class Case:
    format: str
    what: str  # the damage done
    cmd: str
    argv: list[str]
    names: list[str]  # the damaged file's name (and its folder): the error must mention one
    result: dict = field(default_factory=dict)
    verdict: str = ""  # "error" (as it should), "accepted", or "FAILED: why"


def judge(case: Case) -> str:
    code, output = case.result.get("code"), case.result.get("output", "")
    if not isinstance(code, int):
        return f"FAILED: {code}"
    if "Traceback (most recent call last)" in output or "unexpected error" in output:
        return "FAILED: traceback"
    if CONTROL in case.what:
        return "control" if code == 0 else f"FAILED: the undamaged control exited {code}"
    if code == 0:
        return "accepted"
    if code not in (1, 2):
        return f"FAILED: exit code {code}"
    lines = [line for line in output.splitlines() if line.strip()]
    named = [line for line in lines if any(name in line for name in case.names)]
    if not named:
        return "FAILED: no line names the file"
    return "error"


class Maker:
    """Builds cases: a fresh copy of a seed, one damage, the command to run. ``fixed``: the fixed
    list of a format (every damage on every file, and one undamaged control, which must pass);
    else one random case."""

    def __init__(self, seeds: dict[str, Path], work: Path, rng: random.Random):
        self.seeds, self.work, self.rng = seeds, work, rng
        self.count = 0

    def fresh(self, seed: Path) -> Path:
        self.count += 1
        target = self.work / f"case{self.count:05d}" / seed.name
        target.parent.mkdir(parents=True)
        (shutil.copytree if seed.is_dir() else shutil.copy2)(seed, target)
        return target

    def out(self) -> str:
        return str(self.work / f"case{self.count:05d}" / "out")

    def pick(self, fixed: bool, kinds: list) -> list:
        return [*kinds, CONTROL] if fixed else [self.rng.choice(kinds)]

    def train_args(self, data: Path, fmt: str) -> list[str]:
        """stg-train on ``data``: one iteration on 32-pixel images (what the files are, not training)."""
        return ["--data", str(data), "--format", fmt, "--out", self.out(), "--iters", "1", "--preset", "fast",
                "--size", "32", "--no-progress"]  # fmt: skip

    # -- per format ---------------------------------------------------------------------------------

    def launch(self, fixed: bool) -> list[Case]:
        files = {
            "demo.yaml": [],
            "replay_zju.yaml": ["data_root:=/tmp"],
            "live_v4l2.yaml": [],
            "live_oak.yaml": [],
            "regression.yaml": ["session:=/tmp/session.mcap", "out:=/tmp/out", "iters:=6"],
            "views.yaml": [],
        }
        files = {name: args for name, args in files.items() if (ROOT / "launch" / name).is_file()}
        cases = []
        for name in sorted(files) if fixed else [self.rng.choice(sorted(files))]:
            for how in self.pick(fixed, [*YAML_DAMAGE, *BYTE_DAMAGE]):
                path = self.fresh(ROOT / "launch") / name  # the whole folder: files include others
                if how in YAML_DAMAGE:
                    what = damage_yaml(path, how, self.rng)
                else:
                    what = damage_bytes(path, how, self.rng)
                argv = ["--validate", str(path), *files[name]]
                cases.append(Case("launch", what, "stg-launch", argv, [path.name]))
        return cases

    def poses(self, fixed: bool) -> list[Case]:
        keys = ("poses", "Rh", "Th", "shapes", "confidence", "K", "frames")
        kinds = [(k, h) for k in keys for h in ARRAY_DAMAGE] + [(None, h) for h in BYTE_DAMAGE]
        cases = []
        for pair in self.pick(fixed, kinds):
            key, how = pair if pair != CONTROL else (None, CONTROL)
            path = self.fresh(self.seeds["poses"])
            what = damage_file(path, key, how, self.rng)
            argv = [str(self.seeds["run"]), "--poses", str(path), "-o", self.out(), "--frames", "2",
                    "--size", "32", "--no-progress"]  # fmt: skip
            cases.append(Case("poses", what, "stg-render", argv, [path.name]))
        return cases

    def dataset(self, fmt: str, fixed: bool) -> list[Case]:
        seed = self.seeds[fmt]
        files = sorted(p.relative_to(seed) for p in seed.rglob("*") if p.is_file())
        structured = [f for f in files if f.suffix in (".npy", ".npz", ".json")]
        images = [f for f in files if f.suffix in (".jpg", ".png")]
        image_damage = ("empty", "truncate_50", "random", "flip")

        def damages(f: Path) -> tuple:
            if f.suffix in (".npy", ".npz"):
                return ARRAY_DAMAGE + BYTE_DAMAGE
            if f.suffix == ".json":
                return JSON_DAMAGE + BYTE_DAMAGE
            return (*image_damage, "remove", "wrong_size")

        if fixed:
            kinds = [(f, h) for f in structured for h in damages(f)]
            kinds += [(f, h) for f in images[:2] for h in image_damage]
            kinds += [(images[0], "remove"), (images[0].parent, "remove_folder"), (images[0], "wrong_size")]
            kinds.append((files[0], CONTROL))
        else:
            f = self.rng.choice(files)
            kinds = [(f, self.rng.choice(damages(f)))]
        cases = []
        for rel, how in kinds:
            root = self.fresh(seed)
            path = root / rel
            if how == "remove":
                path.unlink()
                what = f"{rel}: removed"
            elif how == "remove_folder":
                shutil.rmtree(path)
                what = f"{rel}/: removed"
            elif how == "wrong_size":
                import cv2

                image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
                cv2.imwrite(str(path), image[: image.shape[0] // 2])
                what = f"{rel}: half the height of the others"
            else:
                what = damage_file(path, None, how, self.rng)
            names = [path.name, str(rel), str(path.parent.name)]
            what = what if what.startswith(str(rel)) else f"{rel}: {what}"
            train = self.train_args(root, {"thuman4": "thuman"}.get(fmt, fmt))
            cases.append(Case(fmt, what, "stg-train", train, names))
        return cases

    def smpl(self, fixed: bool) -> list[Case]:
        with np.load(self.seeds["smpl_npz"], allow_pickle=False) as data:
            keys = sorted(data.files)
        kinds = [("smpl_npz", k, h) for k in keys for h in ARRAY_DAMAGE]
        kinds += [(s, None, h) for s in ("smpl_npz", "smpl_pkl") for h in BYTE_DAMAGE]
        if fixed:
            kinds += [("smpl_npz", None, CONTROL), ("smpl_pkl", None, CONTROL)]
        else:
            kinds = [self.rng.choice(kinds)]
        cases = []
        for seed, key, how in kinds:
            path = self.fresh(self.seeds[seed])
            what = damage_file(path, key, how, self.rng)
            argv = self.train_args(self.seeds["zju"], "zju") + ["--smpl-model", str(path)]
            cases.append(Case("smpl", what, "stg-train", argv, [path.name]))
        return cases

    def mcap(self, fixed: bool) -> list[Case]:
        size = self.seeds["mcap"].stat().st_size
        flips = [f"flip_at_{p}" for p in (8, 30, 100, 300, size // 2, size - 40, size - 10)]
        cases = []
        for how in self.pick(fixed, [*BYTE_DAMAGE, *flips]):
            path = self.fresh(self.seeds["mcap"])
            if how.startswith("flip_at_"):
                raw = bytearray(path.read_bytes())
                at = min(int(how.split("_")[-1]), len(raw) - 1)
                raw[at : at + 8] = b"\xff" * len(raw[at : at + 8])
                path.write_bytes(bytes(raw))
                what = f"{path.name}: 8 bytes set to 0xff at {at}"
            else:
                what = damage_file(path, None, how, self.rng)
            cases.append(Case("mcap", what, "stg-bag", ["info", str(path)], [path.name]))
            export = ["export", str(path), "-o", self.out(), "--topic", "avatar/image"]
            cases.append(Case("mcap", what + " (export)", "stg-bag", export, [path.name]))
        return cases

    def intrinsics(self, fixed: bool) -> list[Case]:
        special = {
            "k_singular": {"K": [[0, 0, 0], [0, 0, 0], [0, 0, 1]]},
            "k_negative": {"K": [[-60, 0, 32], [0, -60, 32], [0, 0, 1]]},
            "dist_long": {"K": [[60, 0, 32], [0, 60, 32], [0, 0, 1]], "dist": [0.1] * 100},
            "k_2x2": {"K": [[60, 0], [0, 60]]},
            "r_mirror": {"K": [[60, 0, 32], [0, 60, 32], [0, 0, 1]], "R": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]},
        }
        cases = []
        for how in self.pick(fixed, [*JSON_DAMAGE, *BYTE_DAMAGE, *special]):
            path = self.fresh(self.seeds["intrinsics"])
            if how in special:
                path.write_text(json.dumps(special[how]))
                what = f"{path.name}: {how}"
            else:
                what = damage_file(path, None, how, self.rng)
            track = [str(self.seeds["video"]), "--out", self.out() + "/POSES.npz", "--intrinsics", str(path),
                     "--no-progress"]  # fmt: skip
            cases.append(Case("intrinsics", what, "stg-track", track, [path.name]))
            # the live ingest's calibration: one frame of the video, on a bus nobody listens to
            params = {"source": "video", "path": str(self.seeds["video"]), "calibration": str(path),
                      "max_frames": 1, "wait_subscribers_s": 0}  # fmt: skip
            ingest = [
                "ingest",
                "--bus",
                f"ipc://{self.out()}-bus",
                "--heartbeat",
                "0",
                "--params",
                json.dumps(params),
            ]
            cases.append(Case("intrinsics", what + " (ingest)", "stg-node", ingest, [path.name]))
        return cases

    def rig(self, fixed: bool) -> list[Case]:
        """A rig.json (stg-calibrate's output) read by multi-view stg-track, two views of the seed video."""
        good = json.loads(self.seeds["rig"].read_text())
        a = good["cameras"]["a"]
        special = {
            "no_cameras": {"cameras": {}},
            "cameras_list": {"cameras": [a, a]},
            "r_not_rotation": {"cameras": {"a": a, "b": {**a, "R": [[2, 0, 0], [0, 1, 0], [0, 0, 1]]}}},
            "t_short": {"cameras": {"a": a, "b": {**a, "t": [0, 1]}}},
            "k_singular": {"cameras": {"a": a, "b": {**a, "K": [[0, 0, 0], [0, 0, 0], [0, 0, 1]]}}},
            "image_size_zero": {"cameras": {"a": a, "b": {**a, "image_size": [0, 64]}}},
            "dist_long": {"cameras": {"a": a, "b": {**a, "dist": [0.1] * 100}}},
            "nan_t": {"cameras": {"a": a, "b": {**a, "t": [float("nan"), 0, 1]}}},
        }
        cases = []
        for how in self.pick(fixed, [*JSON_DAMAGE, *BYTE_DAMAGE, *special]):
            path = self.fresh(self.seeds["rig"])
            if how in special:
                path.write_text(json.dumps(special[how]))
                what = f"{path.name}: {how}"
            else:
                what = damage_file(path, None, how, self.rng)
            video = str(self.seeds["video"])
            argv = [
                video,
                video,
                "--calibration",
                str(path),
                "--out",
                self.out() + "/POSES.npz",
                "--no-progress",
            ]
            cases.append(Case("rig", what, "stg-track", argv, [path.name]))
        return cases

    def build(self, fmt: str, fixed: bool) -> list[Case]:
        if fmt in ("zju", "thuman4", "folder"):
            return self.dataset(fmt, fixed)
        return getattr(self, fmt)(fixed)


CONTROL = "control (undamaged)"


def damage_file(path: Path, key: str | None, how: str, rng: random.Random) -> str:
    """One damage to one file, by its kind (bytes, .npz member, .npy, JSON); the control: none."""
    if how == CONTROL:
        return f"{path.name}: {CONTROL}"
    if how in BYTE_DAMAGE:
        return damage_bytes(path, how, rng)
    if path.suffix == ".npz" or path.suffix == ".pkl" and how in ARRAY_DAMAGE:
        return damage_npz(path, key, how, rng)
    if path.suffix == ".npy":
        return damage_npy(path, how, rng)
    return damage_json(path, how, rng)


def rig_available() -> bool:
    import importlib.util

    return any(importlib.util.find_spec(m) is not None for m in ("stg_node.nodes.rig", "stg_node.data.rig"))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--formats", default=",".join(FORMATS), help="which formats (default: all)")
    parser.add_argument(
        "--cases", type=int, default=40, help="random cases per format, beyond the fixed list"
    )
    parser.add_argument("--no-fixed", action="store_true", help="only the random cases")
    parser.add_argument("--seed", type=int, default=0, help="random seed")
    parser.add_argument("--timeout", type=float, default=180.0, help="seconds a case may take")
    parser.add_argument("--work", type=Path, help="work folder (default: a temp folder, removed at the end)")
    parser.add_argument("--json", type=Path, help="also write every case's result here")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return worker()
    formats = {f.strip() for f in args.formats.split(",") if f.strip()}
    if formats - set(FORMATS):
        parser.error(f"unknown formats {sorted(formats - set(FORMATS))}; known: {', '.join(FORMATS)}")
    if "rig" in formats and not rig_available():
        print("fuzz: no rig JSON reader in this checkout: rig skipped", flush=True)
        formats.discard("rig")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "STG_THREADS": "1", "STG_LOG_LEVEL": "WARNING"}
    keep = args.work is not None
    work = args.work or Path(tempfile.mkdtemp(prefix="stgfuzz-"))
    rng = random.Random(args.seed)
    try:
        seeds = build_seeds(work / "seeds", formats, env)
        shutil.rmtree(work / "cases", ignore_errors=True)  # (seeds are kept: they take a while)
        (work / "cases").mkdir(parents=True)
        maker = Maker(seeds, work / "cases", rng)
        cases: list[Case] = []
        for fmt in [f for f in FORMATS if f in formats]:
            if not args.no_fixed:
                cases += maker.build(fmt, fixed=True)
            for _ in range(args.cases):
                cases += maker.build(fmt, fixed=False)
        print(f"fuzz: {len(cases)} cases over {', '.join(sorted(formats))}", flush=True)
        runner = Worker(env)
        started = time.monotonic()
        try:
            for i, case in enumerate(cases, 1):
                case.result = runner.run(case.cmd, case.argv, args.timeout)
                case.verdict = judge(case)
                if case.verdict.startswith("FAILED"):
                    tail = case.result.get("output", "").strip().splitlines()[-3:]
                    print(
                        f"  {case.format}: {case.what}: {case.verdict}\n      " + "\n      ".join(tail),
                        flush=True,
                    )
                if i % 50 == 0:
                    print(f"fuzz: {i}/{len(cases)} cases, {time.monotonic() - started:.0f} s", flush=True)
        finally:
            runner.kill()
    finally:
        if not keep:
            shutil.rmtree(work, ignore_errors=True)
    table: dict[str, Counter] = {}
    for case in cases:
        table.setdefault(case.format, Counter())[case.verdict.split(":")[0]] += 1
    print(f"{'format':12} {'cases':>6} {'error':>6} {'accepted':>9} {'control':>8} {'FAILED':>7}")
    for fmt, counts in table.items():
        total = sum(counts.values())
        row = f"{counts['error']:6d} {counts['accepted']:9d} {counts['control']:8d} {counts['FAILED']:7d}"
        print(f"{fmt:12} {total:6d} {row}")
    failed = [c for c in cases if c.verdict.startswith("FAILED")]
    print(f"{len(cases)} cases, {len(failed)} failed")
    if args.json:
        args.json.write_text(json.dumps([asdict(c) for c in cases], indent=1, default=str) + "\n")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
