"""A real multi-node Ray cluster on this machine, every node on 127.0.0.1 (tests and bench).

``ray.cluster_utils.Cluster`` starts a head and worker nodes as separate raylets, each with its own
CPU count, so tasks are scheduled over nodes, and a node can be removed (its processes killed) in
the middle of a job. Ray turns 127.0.0.1 into the machine's interface address unless it believes
it runs where clusters are off (its ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER`` switch, read by the
driver's ``ray._private.ray_constants`` and by every process the nodes start): with it off, every
node, the driver and its connections stay on the loopback address.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Sequence
from typing import Any


@contextlib.contextmanager
def loopback_cluster(cpus: Sequence[int] = (1, 1)) -> Iterator[tuple[Any, list[Any]]]:
    """``(cluster, worker_nodes)``: a head without CPUs (the driver and the job's queue live
    there, no task) and one worker node per entry of ``cpus``; torn down at the end."""
    import ray
    from ray._private import ray_constants
    from ray.cluster_utils import Cluster

    env = os.environ.get("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER")
    flag = ray_constants.ENABLE_RAY_CLUSTER
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    ray_constants.ENABLE_RAY_CLUSTER = False
    loop = "127.0.0.1"
    cluster = Cluster(
        initialize_head=True,
        head_node_args={"num_cpus": 0, "include_dashboard": False, "node_ip_address": loop},
    )
    try:
        nodes = [cluster.add_node(num_cpus=n, node_ip_address=loop) for n in cpus]
        cluster.wait_for_nodes()
        yield cluster, nodes
    finally:
        if ray.is_initialized():
            ray.shutdown()
        cluster.shutdown()
        ray_constants.ENABLE_RAY_CLUSTER = flag
        if env is None:
            os.environ.pop("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", None)
        else:
            os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = env


def remove_node_now(cluster: Any, node: Any, timeout: float = 60.0) -> None:
    """Remove ``node`` as a machine going away would: its raylet and every process under it (the
    task workers among them) killed, and only then return. ``Cluster.remove_node`` kills the
    raylet and leaves its workers to notice on their own, so a worker in the middle of a task can
    still finish it and send its result for a while after the node is gone."""
    import select
    import signal

    from ray._private import ray_constants

    raylets = node.all_processes.get(ray_constants.PROCESS_TYPE_RAYLET, [])
    under = _descendants({info.process.pid for info in raylets})
    cluster.remove_node(node, allow_graceful=False)
    for pid in sorted(under):
        try:
            fd = os.pidfd_open(pid)
        except ProcessLookupError:
            continue
        try:
            signal.pidfd_send_signal(fd, signal.SIGKILL)
        except ProcessLookupError:
            pass
        ready, _, _ = select.select([fd], [], [], timeout)  # readable once the process ended
        os.close(fd)
        if not ready:
            raise RuntimeError(f"process {pid} of the removed node still runs after {timeout} s")


def _descendants(roots: set[int]) -> set[int]:
    """Every live process below ``roots`` (from /proc's parent ids)."""
    parent: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                stat = fh.read()
        except OSError:
            continue
        parent[int(entry)] = int(stat.rsplit(")", 1)[1].split()[1])
    found, frontier = set(), set(roots)
    while frontier:
        frontier = {p for p, pp in parent.items() if pp in frontier} - found
        found |= frontier
    return found
