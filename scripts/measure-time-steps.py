#!/usr/bin/env python3
"""Steps per second a local 2x2 wall plays a 16-step time series, and the frames that waited.

For each N (default 64 and 256): writes 16 NRRD steps of a moving sphere at N^3 float32 with the
`play_steps` example (`--dir`), a wall config of four local nodes (2x2 tiles of TILE_W x TILE_H,
AO samples 0, `source = "steps-N/step_*.nrrd"`, `[volume] cache_bytes`), then runs
`isowall up CONFIG --play --frames FRAMES --degrees-per-frame 0` (one step a frame, the camera
still) and prints its report: fps, frames that waited for their step, the nodes' memory.

Usage: scripts/measure-time-steps.py [BIN_DIR] [N[:CACHE_MIB] ...]
  BIN_DIR: target/debug (needs isowall, isowalld and examples/play_steps:
  `cargo build -p isowall -p isowalld && cargo build -p isowall-volume --example play_steps`)
  N:CACHE_MIB: default 64:64 256:256 (cache_bytes in MiB; 0: no steps loaded ahead)
Environment: FRAMES (64), TILE_W (160), TILE_H (90), MODE (screen; object: each node plays its
brick of every step), AO (AO samples, 0), IBL (none; bent with AO), KEEP=1 keeps the work folder.
"""
import os, re, shutil, subprocess, sys, tempfile, time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from local_wall import free_ports  # noqa: E402

args = sys.argv[1:]
BIN = os.path.abspath(args.pop(0) if args and not re.match(r"^\d", args[0]) else "target/debug")


def run_of(a):
    n, _, cache = a.partition(":")
    return int(n), int(cache) if cache else 256


runs = [run_of(a) for a in args] or [(64, 64), (256, 256)]
FRAMES = int(os.environ.get("FRAMES", "64"))
TW, TH = int(os.environ.get("TILE_W", "160")), int(os.environ.get("TILE_H", "90"))
MODE = os.environ.get("MODE", "screen")
AO = int(os.environ.get("AO", "0"))
IBL = os.environ.get("IBL", "none")
if MODE not in ("screen", "object"):
    sys.exit(f"MODE={MODE}: screen or object")
STEPS = 16
for exe in ["isowall", "isowalld", "examples/play_steps"]:
    if not os.path.exists(os.path.join(BIN, exe)):
        sys.exit(f"{BIN}/{exe} is missing: cargo build -p isowall -p isowalld && "
                 "cargo build -p isowall-volume --example play_steps")
work = tempfile.mkdtemp(prefix="isowall-steps-")


def config(n, cache_mib):
    ports = free_ports(4)
    s = (f'[wall]\nname = "steps-{n}"\nmode = "{MODE}"\ndeadline_ms = 30000\nmessage_limit_bytes = 67108864\n\n'
         f'[camera]\nup = [0, 0, 1]\nfov_y = 35.0\n\n'
         f'[volume]\nsource = "steps-{n}/step_*.nrrd"\niso = 0.0\ncache_bytes = {cache_mib << 20}\n\n'
         f'[render]\nao_samples = {AO}\nibl = "{IBL}"\nenv = "sky"\n\n[certificates]\ndir = "keys"\n')
    for i, port in enumerate(ports):
        cx, cy = i % 2, i // 2
        s += (f'\n[[tiles]]\nname = "t{cx}{cy}"\nx = {cx * TW}\ny = {cy * TH}\nwidth = {TW}\nheight = {TH}\n'
              f'\n[[nodes]]\nname = "node{i}"\naddress = "127.0.0.1:{port}"\ntiles = ["t{cx}{cy}"]\n')
    path = os.path.join(work, f"steps-{n}.toml")
    with open(path, "w") as f:
        f.write(s)
    return path


print(f"2x2 wall of {TW}x{TH} tiles in {MODE} space (local nodes, lavapipe where no GPU), AO samples {AO}, IBL {IBL}, "
      f"{STEPS} steps, {FRAMES} frames, one step a frame, camera still; work folder {work}")
for n, cache_mib in runs:
    t = time.time()
    subprocess.run([os.path.join(BIN, "examples/play_steps"), str(n), str(STEPS), "0", "0",
                    "--dir", os.path.join(work, f"steps-{n}")], check=True, capture_output=True)
    wrote = time.time() - t
    cfg = config(n, cache_mib)
    subprocess.run([os.path.join(BIN, "isowall"), "keygen", "--config", cfg], check=True, capture_output=True)
    cmd = [os.path.join(BIN, "isowall"), "up", cfg, "--play", "--frames", str(FRAMES), "--degrees-per-frame", "0"]
    t = time.time()
    out = subprocess.run(cmd, cwd=work, capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{out.stdout}\n{out.stderr}")
    print(f"\n== {n}^3 x {STEPS} steps ({n ** 3 * 4 / 2 ** 20:.0f} MiB a step, written in {wrote:.1f} s), "
          f"cache_bytes {cache_mib} MiB; `isowall up` took {time.time() - t:.1f} s")
    print(out.stdout.rstrip())
if os.environ.get("KEEP") != "1":
    shutil.rmtree(work, ignore_errors=True)
