"""A Ray that a driver starts for itself (`workers.cluster.start_local`, the demo's and a local
job's): its node on loopback, every port of its processes listening there only, and its session
folder its own, even in a process that imported Ray before."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.support.paths import REPO

PROBE = """
import json, os
import ray  # imported first, as a test process or a plugin may have done
from ray.thirdparty_files import psutil
from workers.cluster import session_folder, start_local

context = start_local(num_cpus=1)
session = context.address_info["session_dir"]
assert ray.get(ray.remote(lambda: os.getpid()).remote()) > 0
listening = []
for proc in psutil.process_iter():
    try:
        if session_folder() in " ".join(proc.cmdline()) or proc.pid == os.getpid():
            listening += [c.laddr.ip for c in proc.net_connections("tcp") if c.status == "LISTEN"]
    except (psutil.Error, OSError):
        pass
print(json.dumps({"node": ray.util.get_node_ip_address(), "session": session,
                  "folder": session_folder(), "listening": listening}))
ray.shutdown()
"""


def test_a_local_ray_listens_on_loopback_only_in_a_session_folder_of_its_own():
    run = subprocess.run(
        [sys.executable, "-c", PROBE], cwd=REPO, capture_output=True, text=True, timeout=180
    )
    assert run.returncode == 0, run.stderr[-3000:]
    found = json.loads(run.stdout.strip().splitlines()[-1])
    assert found["node"] == "127.0.0.1"
    assert found["session"].startswith(found["folder"] + "/session_")
    assert len(found["folder"]) + 60 < 107  # room for Ray's socket names under it
    assert len(found["listening"]) >= 3, found
    assert set(found["listening"]) <= {"127.0.0.1", "::ffff:127.0.0.1", "::1"}, found
