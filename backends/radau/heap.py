"""The C heap's free pages handed back to the system (glibc's ``malloc_trim``) in solves of many unknowns.

After a model's compile glibc's mmap threshold stands at its largest (32 MB: it rises to each large block freed),
so a solve's arrays come from the heap, and the pages of those it frees stay resident for the process's life.
"""

from __future__ import annotations

import ctypes
import functools

# Unknowns from which a solve hands the pages its setup freed back to the system before the factors' buffers are
# reserved, and each step's nodes' pages as the dense output joins them (.records.Records.join: the resident set
# held them beside the joined array, a cold solve with the dense output at 10^5 unknowns 3.04 -> 2.76x its factors
# beside its outputs) (glibc's malloc_trim, ~0.1 ms a call there; after each step instead, 2.14 -> 2.04x without
# the dense output, but 12,000 more page faults a solve, ~6 % of its CPU: not done).  At 10^5 unknowns of
# reaction-diffusion a first solve's setup (the model's casadi graphs, the fill's trial LU) frees tens of MB that
# the allocator would keep resident for the process's life.
# (It lowers what the process holds, not what a solve needs: benchmarks/solve_memory.py, which reads the resident
# set before a solve with the heap's free pages handed back, measures a first solve at 10^5 at 4.6x the factors'
# bytes, the model's one-off pieces included, and a later solve at 2.2x, the factors' reused buffers included.)
TRIM_MIN_UNKNOWNS = 10_000


@functools.cache
def malloc_trim():
    """glibc's ``malloc_trim`` (frees the whole free pages of the C heap), or None where the C library has none
    (or ctypes cannot open the main program: on Windows ``CDLL(None)`` raises TypeError)."""
    try:
        return ctypes.CDLL(None).malloc_trim
    except (AttributeError, OSError, TypeError):
        return None


def hand_back_freed_memory(unknowns: int) -> None:
    """From :data:`TRIM_MIN_UNKNOWNS` on, the C heap's free pages back to the system (see there)."""
    trim = malloc_trim() if unknowns >= TRIM_MIN_UNKNOWNS else None
    if trim is not None:
        trim(0)
