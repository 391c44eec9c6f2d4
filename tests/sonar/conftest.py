"""Shared fixtures of the sonar tests: real files (skipped when absent) and a synthetic survey."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "sidescan"
SCOTSMAN = DATA / "scotsman-iver2.xtf"
MBES = DATA / "mbes-lib-150708-R2Testing-0001.xtf"


def need(path: Path) -> Path:
    if not path.is_file():
        pytest.skip(f"real data absent: {path}")
    return path


def rewrite_xtf(src: Path, dst: Path, packet=None, header=None) -> None:
    """``src`` written to ``dst`` as another recorder would have written it: ``header`` edits
    the file header (the first 1024 bytes: two or up to six channels) in place, ``packet``
    takes each sonar packet (bytes) and returns the packet, or the packets, written instead;
    each written packet's size field is set to its length."""
    import struct

    data = src.read_bytes()
    head = bytearray(data[:1024])
    if header is not None:
        header(head)
    out, o = bytearray(head), 1024
    while o + 14 <= len(data):
        kind, size = data[o + 2], struct.unpack_from("<I", data, o + 10)[0]
        written = data[o:o + size]
        if kind == 0 and packet is not None:
            written = packet(written)
        for one in ([written] if isinstance(written, (bytes, bytearray)) else written):
            one = bytearray(one)
            struct.pack_into("<I", one, 10, len(one))
            out += one
        o += size
    dst.write_bytes(bytes(out))


@pytest.fixture(scope="session")
def scotsman_pings():
    from adaptnav.sonar.xtf import read_xtf

    pings, report = read_xtf(need(SCOTSMAN))
    return pings, report


def straight_pass(renderer, rng, start_n_m, yaw_rad, n_pings, ds_m=0.2, speed_m_s=1.5,
                  altitude_m=7.0):
    """Pings along a straight line; returns (pings, positions (P, 2))."""
    f = np.array([math.cos(yaw_rad), math.sin(yaw_rad)])
    pos = np.asarray(start_n_m, float) + np.outer(np.arange(n_pings) * ds_m, f)
    pings = renderer.render_track(np.arange(n_pings) * ds_m / speed_m_s, pos, yaw_rad,
                                  altitude_m, rng, speed_m_s)
    return pings, pos
