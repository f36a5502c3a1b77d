"""MuJoCo's own viewers on a model with sdfzoo's contacts hooked in: the passive viewer driven by the user's loop
and the managed viewer's own loop, each in a child process on a virtual display (Xvfb; skipped without it).
A ball whose collision shape is a zoo.Sphere comes to rest on the plane in both: the contacts reach MuJoCo's solver."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

pytest.importorskip("mujoco")

MODEL = '''
import os, threading, time, mujoco, mujoco.viewer, zoo, zoo.sim
xml = """<mujoco><worldbody><light pos="0 0 1"/><geom type="plane" size="1 1 0.1"/>
  <body name="ball" pos="0 0 0.1"><freejoint/><geom type="sphere" size="0.05" contype="0" conaffinity="0" mass="0.3"/></body>
</worldbody></mujoco>"""
model = mujoco.MjModel.from_xml_string(xml)
data = mujoco.MjData(model)
world = zoo.sim.attach(model, {"ball": zoo.Sphere(radius=0.05)}, method="fw")
'''
PASSIVE = MODEL + '''
with world.hooked(), mujoco.viewer.launch_passive(model, data) as viewer:
    for _ in range(300):
        mujoco.mj_step(model, data)
        viewer.sync()
print("RESULT", data.time, data.qpos[2], data.ncon, flush=True)
'''
MANAGED = MODEL + '''
def report():  # the managed viewer's loop never returns on its own: read the state, then leave
    deadline = time.time() + 60
    while data.time < 0.5 and time.time() < deadline:
        time.sleep(0.1)
    print("RESULT", data.time, data.qpos[2], data.ncon, flush=True)
    os._exit(0)
threading.Thread(target=report, daemon=True).start()
with world.hooked():
    mujoco.viewer.launch(model, data)
'''


@pytest.fixture
def display():
    """A virtual X display (Xvfb, which says its number once it is ready), stopped afterwards."""
    read, write = os.pipe()
    server = subprocess.Popen(["Xvfb", "-displayfd", str(write), "-screen", "0", "640x480x24", "-nolisten", "tcp"],
                              pass_fds=(write,), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(write)
    try:
        with os.fdopen(read) as pipe:
            number = pipe.readline().strip()
        if not number:
            pytest.fail("Xvfb started but gave no display number")
        yield f":{number}"
    finally:
        server.terminate()
        server.wait(timeout=30)


@pytest.mark.skipif(shutil.which("Xvfb") is None, reason="no Xvfb (Debian's xvfb) for a virtual display")
@pytest.mark.parametrize("script", [PASSIVE, MANAGED], ids=["launch_passive", "launch"])
def test_mujocos_viewers_step_the_hooked_model(tmp_path, display, script):
    env = {**os.environ, "MUJOCO_GL": "glfw", "DISPLAY": display}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=240, env=env,
                          cwd=tmp_path, stdin=subprocess.DEVNULL)
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT")]
    assert lines, done.stdout + done.stderr
    sim_time, height, contacts = (float(x) for x in lines[-1].split()[1:])
    assert sim_time >= 0.5 and abs(height - 0.05) < 1e-3, lines[-1]  # resting on the plane: without them it falls through
    if script is PASSIVE:  # the managed viewer steps in its own thread: its contact count is read mid-step
        assert contacts >= 1, lines[-1]
