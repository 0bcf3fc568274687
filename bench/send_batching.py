"""What one ``sendmmsg`` for a datagram's six skeletons would save over six ``sendto`` calls.

The engine sends each fused skeleton in its own datagram (issue 10: one ``sendto`` per person
and view, about 14 % of the live engine thread's samples at in-step 6x6). Linux can send
several datagrams in one system call (``sendmmsg``), which Python's ``socket`` does not
offer; here it is called through ``ctypes`` (its argument arrays built once, each call
filling in the datagrams' pointers and lengths), beside ``socket.sendto``, to a receiver
in another process blocked in ``recv`` (as a view is: each datagram may wake it), with a
sleep before each group of sends (as the engine thread's sends come after it waited for a
burst). The figure is the sending thread's CPU per group of six 851-byte datagrams (one
6x6 emission to one view), median over the groups, the two ways alternated in rounds.

Run: python bench/send_batching.py [--groups 1000] [--rounds 3]
"""

from __future__ import annotations

import argparse
import ctypes
import socket
import statistics
import struct
import subprocess
import sys
import time


class _Iovec(ctypes.Structure):
    _fields_ = [("base", ctypes.c_void_p), ("len", ctypes.c_size_t)]


class _Msghdr(ctypes.Structure):
    _fields_ = [("name", ctypes.c_void_p), ("namelen", ctypes.c_uint32),
                ("iov", ctypes.POINTER(_Iovec)), ("iovlen", ctypes.c_size_t),
                ("control", ctypes.c_void_p), ("controllen", ctypes.c_size_t),
                ("flags", ctypes.c_int)]


class _Mmsghdr(ctypes.Structure):
    _fields_ = [("hdr", _Msghdr), ("len", ctypes.c_uint)]


class MultiSender:
    """Up to ``size`` datagrams to one IPv4 address in one ``sendmmsg`` call."""

    def __init__(self, sock: socket.socket, address: tuple[str, int], size: int = 64) -> None:
        libc = ctypes.CDLL(None, use_errno=True)
        self.call = libc.sendmmsg
        self.call.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_uint, ctypes.c_int]
        self.call.restype = ctypes.c_int
        self.fd = sock.fileno()
        self.name = ctypes.create_string_buffer(
            struct.pack("=H", socket.AF_INET) + struct.pack("!H", address[1])
            + socket.inet_aton(address[0]) + bytes(8), 16)
        self.iov = (_Iovec * size)()
        self.msgs = (_Mmsghdr * size)()
        for k in range(size):
            hdr = self.msgs[k].hdr
            hdr.iov, hdr.iovlen = ctypes.pointer(self.iov[k]), 1
            hdr.name, hdr.namelen = ctypes.addressof(self.name), 16

    def send(self, datagrams: list[bytes]) -> int:
        iov = self.iov
        for k, data in enumerate(datagrams):
            entry = iov[k]
            entry.base = ctypes.cast(data, ctypes.c_void_p).value
            entry.len = len(data)
        return self.call(self.fd, self.msgs, len(datagrams), 0)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--groups", type=int, default=1000)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--sleep", type=float, default=0.002, help="s before each group")
    args = parser.parse_args()
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    address = sink.getsockname()
    sink.close()
    view = subprocess.Popen([sys.executable, "-c", (
        "import socket\n"
        "s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)\n"
        f"s.bind(('127.0.0.1', {address[1]}))\n"
        "while True:\n    s.recv(65536)\n")])
    try:
        time.sleep(0.5)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        multi = MultiSender(sock, address)
        group = [bytes([k]) * 851 for k in range(6)]
        if multi.send(group) != len(group):
            print("sendmmsg did not send the group", file=sys.stderr)
            return 1

        def plain() -> None:
            for data in group:
                sock.sendto(data, address)

        ways = {"sendto x6": plain, "sendmmsg (ctypes)": lambda: multi.send(group)}
        cpu: dict[str, list[float]] = {name: [] for name in ways}
        for _ in range(args.rounds):
            for name, way in ways.items():
                for _ in range(args.groups):
                    time.sleep(args.sleep)
                    t0 = time.thread_time()
                    way()
                    cpu[name].append(time.thread_time() - t0)
        for name, samples in cpu.items():
            us = sorted(s * 1e6 for s in samples)
            print(f"{name:18s} CPU a group of 6: p50 {statistics.median(us):6.1f} us, "
                  f"p90 {us[int(0.9 * len(us))]:6.1f} us ({len(us)} groups)")
        ratio = statistics.median(cpu["sendmmsg (ctypes)"]) / statistics.median(cpu["sendto x6"])
        print(f"sendmmsg / sendto: {ratio:.2f}")
    finally:
        view.kill()
    return 0


if __name__ == "__main__":
    sys.exit(main())
