#!/usr/bin/env python3
# What the console's page asks of the wall, without a browser: fps in 8 s windows with nothing
# asked, with a full-size thumbnail asked twice a second, and with the status asked twice a
# second, in two rounds (urllib only; the wall's nodes are started with --local).
#
# Usage: scripts/measure-console-api.py WALL.toml [BIN_DIR]   (BIN_DIR: target/debug)
import json, os, shutil, signal, subprocess, sys, tempfile, threading, time, urllib.request
if len(sys.argv) < 2:
    sys.exit("usage: scripts/measure-console-api.py WALL.toml [BIN_DIR]")
BIN = os.path.abspath(sys.argv[2] if len(sys.argv) > 2 else "target/debug")
work = tempfile.mkdtemp(prefix="isowall-console-api-")
shutil.copy(sys.argv[1], os.path.join(work, "w.toml"))
os.chdir(work)
subprocess.run([BIN + "/isowall", "keygen", "--config", "w.toml"], check=True, capture_output=True)
con = subprocess.Popen([BIN + "/isowall", "console", "w.toml", "--local", "--listen", "127.0.0.1:18091"],
                       stdout=open("out.txt", "w"), stderr=open("err.txt", "w"))
base = "http://127.0.0.1:18091"
def get(path):
    with urllib.request.urlopen(base + path, timeout=60) as r:
        return r.read()
t0 = time.time()
while True:
    try:
        if all(n["state"] == "up" for n in json.loads(get("/api/status"))["nodes"]):
            break
    except Exception:
        pass
    if time.time() - t0 > 300:
        sys.exit("no wall")
    time.sleep(0.5)
time.sleep(5)
def fps(sec, ask=None):
    stop = threading.Event()
    def asking():
        while not stop.is_set():
            ask()
            stop.wait(0.5)
    th = threading.Thread(target=asking) if ask else None
    if th:
        th.start()
    a = json.loads(get("/api/status")); time.sleep(sec); b = json.loads(get("/api/status"))
    stop.set()
    if th:
        th.join()
    return (b["frame"]["released"] - a["frame"]["released"]) / (b["console"]["uptime_s"] - a["console"]["uptime_s"])
width = json.loads(get("/api/status"))["wall"]["width"]
for _ in range(2):
    idle = fps(8)
    thumb = fps(8, lambda: get(f"/api/snapshot.png?width={width}"))
    status = fps(8, lambda: get("/api/status"))
    print(f"fps: nothing asked {idle:.2f}, a full-size thumbnail at 2 Hz {thumb:.2f}, the status at 2 Hz {status:.2f}", flush=True)
con.send_signal(signal.SIGINT)
time.sleep(3)
