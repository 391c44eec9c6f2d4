"""kalman.median_window_push moves only the sorted values between the oldest's place and the new
one's (one shift, not a removal's and an insertion's): against the sorted list and bisect it
stands for (del s[bisect_left(s, oldest)], insort) on windows of 1, 2 and 7, a new value equal to
the one leaving, ties, zeros and infinities — the sorted half, the ring and the median exactly."""
from __future__ import annotations

import math
from bisect import bisect_left, insort
from collections import deque

import numpy as np
import pytest

from adaptnav.fusion import kalman


@pytest.mark.parametrize("W", [1, 2, 7])
def test_one_shift_is_the_list_s_removal_and_insertion(W):
    rng = np.random.default_rng(W)
    window = np.zeros(2 + 2 * W)
    ring, srt = deque(maxlen=W), []
    pool = [0.0, 0.5, 1.0, 1.0, 2.0, math.inf, 1e-300, 3.0]
    for k in range(4000):
        if k % 5 == 0 and ring:
            v = ring[0]  # the value leaving comes back
        else:
            v = float(rng.choice(pool)) if k % 3 else float(abs(rng.normal()))
        if len(ring) == W:
            del srt[bisect_left(srt, ring[0])]
        ring.append(v)
        insort(srt, v)
        n, med = kalman.median_window_push(window, v)
        assert n == len(srt) and (med == np.median(srt) or (math.isnan(med) and math.isnan(np.median(srt))))
        assert window[2 + W:2 + W + n].tolist() == srt
        head, arrival = int(window[1]), window[2:2 + W].tolist()
        assert (arrival[head:] + arrival[:head] if n == W else arrival[:n]) == list(ring)
