"""Who owns a local UDP sender: the relay's MAVSDK side takes only a socket of this process's own tree.

Any local process can send to the relay's port on 127.0.0.1 (the port is listed in ``/proc/net/udp``), so
arriving first proves nothing. The kernel knows whose socket a datagram came from: the socket bound to
the sender's port has an owner (uid) and an inode, and the inode is among the open files of the process
that holds it. MAVSDK's server is a child of the service (or the service itself), so a sender is taken only
when its socket belongs to this process or one of its descendants. Linux only; elsewhere the check says
it cannot tell, and the relay falls back to the first sender.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

_PROC = Path("/proc")
Addr = tuple[str, int]
#: Refused local senders remembered (each new one costs a look at /proc).
MAX_REFUSED = 64
#: Local addresses a socket that sends from 127.0.0.1 may be bound to (hex, as /proc/net/udp writes them).
_LOOPBACK_OR_ANY = {"0100007F", "00000000"}
_LOOPBACK_OR_ANY6 = {
    "00000000000000000000000000000000",
    "0000000000000000FFFF00000100007F",
    "00000000000000000000000001000000",
}


def socket_inodes(port: int, proc: Path = _PROC) -> list[tuple[int, int]] | None:
    """(uid, inode) of each UDP socket bound to ``port`` on loopback or any address; None without /proc."""
    found: list[tuple[int, int]] = []
    readable = False
    for name, local_ips in (("udp", _LOOPBACK_OR_ANY), ("udp6", _LOOPBACK_OR_ANY6)):
        try:
            lines = (proc / "net" / name).read_text().splitlines()[1:]
        except OSError:
            continue
        readable = True
        for line in lines:
            fields = line.split()
            if len(fields) < 10:
                continue
            ip, _, port_hex = fields[1].partition(":")
            if int(port_hex, 16) == port and ip.upper() in local_ips:
                found.append((int(fields[7]), int(fields[9])))
    return found if readable else None


def process_tree(root_pid: int, proc: Path = _PROC) -> set[int]:
    """``root_pid`` and every process descended from it."""
    children: dict[int, list[int]] = {}
    for entry in proc.iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue  # gone meanwhile
        # "pid (comm) state ppid ...": comm may hold spaces and parentheses, so split after the last ')'.
        rest = stat[stat.rfind(")") + 2 :].split()
        if len(rest) >= 2:
            children.setdefault(int(rest[1]), []).append(int(entry.name))
    tree, todo = {root_pid}, [root_pid]
    while todo:
        for child in children.get(todo.pop(), []):
            if child not in tree:
                tree.add(child)
                todo.append(child)
    return tree


def holds_inode(pid: int, inode: int, proc: Path = _PROC) -> bool:
    """Does process ``pid`` have socket ``inode`` open?"""
    want = f"socket:[{inode}]"
    try:
        fds = os.listdir(proc / str(pid) / "fd")
    except OSError:
        return False
    for fd in fds:
        try:
            if os.readlink(proc / str(pid) / "fd" / fd) == want:
                return True
        except OSError:
            continue
    return False


def sender_problem(addr: Addr, proc: Path = _PROC) -> str | None:
    """Why a local sender at ``addr`` is not the service's own MAVSDK; None when it is (or cannot be told).

    Blocking reads of /proc (a few milliseconds): the relay asks once per new address, until MAVSDK's
    own socket has spoken.
    """
    if addr[0] != "127.0.0.1":
        return f"{addr[0]} is not the loopback address"
    owners = socket_inodes(addr[1], proc)
    if owners is None:
        return None  # no /proc: cannot tell
    if not owners:
        return f"no socket bound to port {addr[1]} (gone, or in another network namespace)"
    tree = process_tree(os.getpid(), proc)
    for _uid, inode in owners:
        if any(holds_inode(pid, inode, proc) for pid in tree):
            return None
    uids = ", ".join(sorted({str(uid) for uid, _ in owners}))
    return f"its socket belongs to another process (uid {uids}), not to the service or its MAVSDK"


class MavsdkSide:
    """Which local sender is MAVSDK: the first one the service owns; every other is refused, then and later.

    Args:
        problem: why an address is not the service's (None: it is); :func:`sender_problem` by default.
    """

    def __init__(self, problem: Callable[[Addr], str | None] = sender_problem) -> None:
        self.addr: Addr | None = None
        self._problem = problem
        self._refused: set[Addr] = set()

    def judge(self, addr: Addr) -> tuple[str, str] | None:
        """None: ``addr`` is MAVSDK (now bound to it). Otherwise (counter, one line) for the refusal."""
        if self.addr is not None:
            return (
                "local_foreign",
                f"a second local sender at {_text(addr)} (MAVSDK is {_text(self.addr)}): refused",
            )
        problem = "refused before" if addr in self._refused else self._problem(addr)
        if problem is not None:
            if len(self._refused) < MAX_REFUSED:
                self._refused.add(addr)
            return "local_refused", f"a local sender at {_text(addr)} is not MAVSDK: {problem}"
        self.addr = addr
        return None


def _text(addr: Addr) -> str:
    return f"{addr[0]}:{addr[1]}"
