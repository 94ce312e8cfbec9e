"""CPU quotas for a server's workers (Linux cgroups), for ``bench_load.py --cpu-quota``.

On a machine with as many cores as the load needs, each worker of ``trustlab serve --workers N`` has a core (or
several) of its own. This 2-core machine also runs the bots and PostgreSQL, so two workers cannot each get a core
here. What can be compared here is capacity at an equal CPU allowance per worker: every worker, with the
processes it starts (its 3D view process, the attempt planner), gets at most ``cores`` of CPU time through a cgroup
CPU quota, and the bots, nginx and PostgreSQL run beside them as if on other machines. One process so capped
against two workers so capped approximates the scaling of a machine with a core per worker. A quota is not a core:
a group's processes spend it together, then wait out the period, so each worker is slower than on a core of its
own and the capacities are far lower; what carries over is the ratio, unless the workers contend for something
that is not CPU (the database, nginx, memory bandwidth).

The quota's period is 10 ms, not the kernel's default 100 ms: a group that spent its quota waits for the rest of
the period, and 60 ms waits would show in every latency figure.

Needs root and a writable cgroup CPU controller (cgroup v1 at /sys/fs/cgroup/cpu, or v2 with ``cpu`` enabled).
"""

from __future__ import annotations

import os
from pathlib import Path

PERIOD_US = 10_000
CGROUP_V1 = Path("/sys/fs/cgroup/cpu")
CGROUP_V2 = Path("/sys/fs/cgroup")


def _controller() -> tuple[Path, int]:
    """(the folder in which to create groups, the cgroup version); raises where there is none to write to."""
    if (CGROUP_V1 / "cpu.cfs_quota_us").exists() and os.access(CGROUP_V1, os.W_OK):
        return CGROUP_V1, 1
    controllers = CGROUP_V2 / "cgroup.subtree_control"
    if controllers.exists() and "cpu" in controllers.read_text().split() and os.access(CGROUP_V2, os.W_OK):
        return CGROUP_V2, 2
    raise SystemExit("--cpu-quota needs a writable cgroup CPU controller (run as root; cgroup v1 at "
                     f"{CGROUP_V1}, or v2 with 'cpu' in {controllers})")


class WorkerQuotas:
    """One cgroup per worker, each limited to ``cores`` of CPU time; ``place`` moves processes into them."""

    def __init__(self, cores: float, prefix: str = "trustlab-bench"):
        if cores <= 0:
            raise SystemExit(f"--cpu-quota must be positive, not {cores}")
        self.cores = cores
        self.root, self.version = _controller()
        self.prefix = f"{prefix}-{os.getpid()}"
        self.groups: dict[str, Path] = {}

    def place(self, groups: dict[str, list[int]]) -> None:
        """Move each group's processes into a cgroup of its own (processes they start later follow them)."""
        quota = int(self.cores * PERIOD_US)
        for name, pids in groups.items():
            folder = self.groups.get(name)
            if folder is None:
                folder = self.root / f"{self.prefix}-{name}"
                folder.mkdir(exist_ok=True)
                if self.version == 1:
                    (folder / "cpu.cfs_period_us").write_text(str(PERIOD_US))
                    (folder / "cpu.cfs_quota_us").write_text(str(quota))
                else:
                    (folder / "cpu.max").write_text(f"{quota} {PERIOD_US}")
                self.groups[name] = folder
            for pid in pids:
                try:
                    (folder / "cgroup.procs").write_text(str(pid))
                except OSError:
                    continue  # it ended meanwhile

    def throttled_s(self) -> dict[str, float]:
        """Seconds each group spent waiting for its quota so far."""
        out = {}
        for name, folder in self.groups.items():
            stat = dict(line.split() for line in (folder / "cpu.stat").read_text().splitlines() if line.strip())
            out[name] = int(stat["throttled_time"]) / 1e9 if self.version == 1 else int(stat["throttled_usec"]) / 1e6
        return out

    def close(self) -> None:
        """Move what is left back to the root group and remove the groups."""
        for folder in self.groups.values():
            try:
                for pid in (folder / "cgroup.procs").read_text().split():
                    try:
                        (self.root / "cgroup.procs").write_text(pid)
                    except OSError:
                        continue
                folder.rmdir()
            except OSError:
                continue
        self.groups = {}
