#!/usr/bin/env python3
"""A 2x2 wall on loopback plays a time series: steps per second and the frames that waited.

Usage: scripts/measure-steps.py N STEPS FRAMES MODE [CACHE_MB] [BIN_DIR]
  N: the steps' size (N^3 float32), STEPS: how many (step_0000.nrrd ...), FRAMES: frames played
  (one step a frame, `isowall up --play`, unpaced), MODE: screen or object, CACHE_MB: `[volume]
  cache_bytes` in MiB (default 1024), BIN_DIR: target/debug by default.
Writes a moving ball (as daemon/volume/examples/play_steps.rs does) and a 2x2 wall of 160x120
tiles (AO 4 samples, bent IBL) in a temporary folder, runs `isowall up`, prints its time-step
report and the wall's steps per second (frames over the wall-clock time of the play, start-up
excluded: the time from `isowall up`'s first frame line to its end).
"""
import os, struct, subprocess, sys, tempfile, time, socket

if len(sys.argv) < 5:
    sys.exit(__doc__)
n, steps, frames = (int(a) for a in sys.argv[1:4])
mode = sys.argv[4]
cache_mb = int(sys.argv[5]) if len(sys.argv) > 5 else 1024
BIN = os.path.abspath(sys.argv[6] if len(sys.argv) > 6 else "target/debug")
work = tempfile.mkdtemp(prefix="isowall-steps-")
os.makedirs(os.path.join(work, "steps"))
for k in range(steps):
    c = n * (0.3 + 0.4 * k / steps)
    vals = bytearray()
    for z in range(n):
        for y in range(n):
            dz, dy = z - n / 2, y - n / 2
            vals += struct.pack(f"<{n}f", *[n / 4 - ((x - c) ** 2 + dy * dy + dz * dz) ** 0.5 for x in range(n)])
    with open(os.path.join(work, f"steps/step_{k:04}.nrrd"), "wb") as f:
        f.write(f"NRRD0004\ntype: float\ndimension: 3\nsizes: {n} {n} {n}\nendian: little\nencoding: raw\n\n".encode())
        f.write(vals)
def port():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind(("127.0.0.1", 0)); p = s.getsockname()[1]; s.close(); return p
m = n - 1
cfg = (f'[wall]\nname = "steps"\nmode = "{mode}"\ndeadline_ms = 20000\n\n'
       f'[camera]\neye = [{1.2*m}, {-1.4*m}, {0.9*m}]\ntarget = [{m/2}, {m/2}, {m/2}]\nup = [0, 0, 1]\nfov_y = 40.0\n\n'
       f'[volume]\nsource = "steps/step_*.nrrd"\niso = 0.0\ncache_bytes = {cache_mb << 20}\n\n'
       '[render]\nao_samples = 4\nibl = "bent"\nenv = "sky"\n\n[certificates]\ndir = "keys"\n')
w, h = 160, 120
for i in range(4):
    cx, cy = i % 2, i // 2
    cfg += f'\n[[tiles]]\nname = "t{cx}{cy}"\nx = {cx * w}\ny = {cy * h}\nwidth = {w}\nheight = {h}\n'
    cfg += f'\n[[nodes]]\nname = "node{i}"\naddress = "127.0.0.1:{port()}"\ntiles = ["t{cx}{cy}"]\n'
open(os.path.join(work, "w.toml"), "w").write(cfg)
os.chdir(work)
subprocess.run([BIN + "/isowall", "keygen", "--config", "w.toml"], check=True, capture_output=True)
t0 = time.time()
out = subprocess.run([BIN + "/isowall", "up", "w.toml", "--play", "--frames", str(frames), "--degrees-per-frame", "0",
                      "--start-timeout", "600"], capture_output=True, text=True)
total = time.time() - t0
print(out.stdout)
if out.returncode != 0:
    print(out.stderr)
    sys.exit(f"isowall up failed ({out.returncode}); logs in {work}/logs")
print(f"{n}^3 x {steps} steps, {mode} space, cache {cache_mb} MiB: {frames} frames; isowall up took {total:.1f} s in all; work dir {work}")
