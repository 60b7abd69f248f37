"""What every benchmark records about its run: when, on which machine, with which
package versions and which lodserver code (``machine_info``), and how busy the
machine was (``cpu_busy``); a server's memory and its peak (``process_memory_kib``)."""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
import time
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def machine_info(packages) -> dict:
    """The run's facts; ``versions`` of each of ``packages`` (None when missing)."""
    cpu = next((line.split(":", 1)[1].strip() for line in
                Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.processor())
    versions = {}
    for name in packages:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None

    def git(*args):
        return subprocess.run(["git", "-C", str(ROOT), *args], check=False,
                              capture_output=True, text=True).stdout.strip()

    return {
        "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)),
        "cpu": cpu,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "versions": versions,
        # the machine may be shared; on this VM the load average idles near 2,
        # so cpu_busy() is the better witness where time matters
        "load_average_at_start": os.getloadavg(),
        # someone may be editing lodserver while a benchmark runs: say which code ran
        "git_commit": git("rev-parse", "HEAD"),
        "lodserver_uncommitted": git("status", "--porcelain", "--", "lodserver").splitlines(),
    }


def cpu_busy(seconds: float = 2.0) -> float:
    """Fraction of all CPUs' time spent busy over the next ``seconds`` (Linux)."""
    def sample():
        values = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        return sum(values), values[3] + values[4]  # total, idle + iowait

    total, idle = sample()
    time.sleep(seconds)
    total2, idle2 = sample()
    return 1.0 - (idle2 - idle) / max(total2 - total, 1)


def process_memory_kib(pid: int) -> dict:
    """VmRSS and VmHWM (the peak) of process ``pid``, in KiB, from ``/proc``."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0])
    return out


def reset_memory_peak(pid: int) -> bool:
    """Start process ``pid``'s VmHWM again from its current RSS; False where the
    kernel does not allow it (then a peak includes what came before)."""
    try:
        Path(f"/proc/{pid}/clear_refs").write_text("5")
        return True
    except OSError:
        return False
