"""The host allocator's setting: freed memory kept for the next step on glibc, the system's own on request."""

import json
import os
import platform
import subprocess
import sys

import pytest

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"

#: a process that frees a 256-MB tensor it has written and reports its resident memory before and after
PROBE = """
import json, os
from delta.host_memory import hold_freed_memory
held = hold_freed_memory()
import torch
page = os.sysconf("SC_PAGE_SIZE")
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * page / 2**20
x = torch.ones(64 * 2**20)  # 256 MB, written: resident
during = rss()
del x
print(json.dumps({"held": held, "during": during, "after": rss()}))
"""


def probe(env_value: str | None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "DELTA_HOST_MALLOC"}
    if env_value is not None:
        env["DELTA_HOST_MALLOC"] = env_value
    res = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not GLIBC, reason="the setting is glibc's")
def test_freed_memory_stays_with_the_process_and_goes_back_with_the_systems_setting():
    held, system = probe(None), probe("system")
    assert held["held"] is True and system["held"] is False
    # glibc's own: a 256-MB block is unmapped when freed; held: it stays resident for reuse
    assert system["during"] - system["after"] > 200
    assert held["during"] - held["after"] < 10


def test_an_unknown_setting_is_named():
    env = {**os.environ, "DELTA_HOST_MALLOC": "jemalloc"}
    code = "from delta.host_memory import hold_freed_memory\nhold_freed_memory()"
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode != 0
    assert "DELTA_HOST_MALLOC='jemalloc'" in res.stderr and "'hold'" in res.stderr and "'system'" in res.stderr
