"""LZF decompression (liblzf's format, as used by PCD ``binary_compressed`` data), in plain Python.

LZF (Marc Lehmann's liblzf, BSD) is a byte-oriented LZ77 variant with no header of its own. The
compressed stream is a sequence of tokens, each starting with a control byte ``c``:

- ``c < 32``: a literal run: the next ``c + 1`` bytes are copied to the output;
- otherwise a back reference of length ``(c >> 5) + 2`` (when ``c >> 5 == 7`` one more byte follows and is
  added to the length) and offset ``((c & 31) << 8) + next byte + 1`` bytes behind the current output end.
  Source and destination may overlap, in which case the copy repeats the last ``offset`` bytes
  (byte-by-byte copy semantics).

The decoder below copies whole runs with slices (an overlapping reference becomes a repeated pattern), so
its Python loop runs once per token, not once per byte: a 4.9 MB PCD payload decodes in well under a second.
No PyPI package was used: ``python-lzf`` ships no wheel for this platform (it needs a C compiler) and the
only wheel-building alternative had a single release with no track record.
"""

from __future__ import annotations

__all__ = ["LZFError", "decompress"]


class LZFError(ValueError):
    """The data is not a valid LZF stream (or does not decompress to the expected size)."""


def decompress(data: bytes | bytearray | memoryview, expected_size: int) -> bytes:
    """Decompress an LZF stream.

    Parameters
    ----------
    data : the compressed bytes (no header: PCD's two uint32 sizes must be removed by the caller).
    expected_size : the uncompressed size in bytes; the stream must decode to exactly this many bytes.

    Returns
    -------
    bytes of length ``expected_size``.

    Raises
    ------
    LZFError
        Truncated stream, a back reference before the start of the output, or output longer or shorter
        than ``expected_size``.

    Examples
    --------
    >>> decompress(bytes([2]) + b"abc" + bytes([0x20 | 0, 2]), 6)  # "abc" then copy 3 bytes from 3 back
    b'abcabc'
    """
    src = bytes(data)
    n_in = len(src)
    if expected_size < 0:
        raise LZFError(f"expected size must be >= 0, got {expected_size}")
    out = bytearray()
    ip = 0
    while ip < n_in:
        ctrl = src[ip]
        ip += 1
        if ctrl < 32:  # literal run
            run = ctrl + 1
            if ip + run > n_in:
                raise LZFError(f"truncated LZF stream: a literal run of {run} bytes at input offset {ip - 1} "
                               f"goes past the end ({n_in} bytes)")
            out += src[ip:ip + run]
            ip += run
        else:  # back reference
            length = ctrl >> 5
            if length == 7:
                if ip >= n_in:
                    raise LZFError(f"truncated LZF stream: back reference at input offset {ip - 1} lacks its "
                                   "length byte")
                length += src[ip]
                ip += 1
            if ip >= n_in:
                raise LZFError(f"truncated LZF stream: back reference at input offset {ip - 1} lacks its "
                               "offset byte")
            offset = ((ctrl & 0x1F) << 8) + src[ip] + 1
            ip += 1
            length += 2
            start = len(out) - offset
            if start < 0:
                raise LZFError(f"invalid LZF stream: back reference {offset} bytes behind output position "
                               f"{len(out)} (input offset {ip})")
            if offset >= length:
                out += out[start:start + length]
            else:  # overlapping: the last `offset` bytes repeat
                pattern = bytes(out[start:])
                reps = -(-length // offset)
                out += (pattern * reps)[:length]
        if len(out) > expected_size:
            raise LZFError(f"LZF stream decodes to more than the expected {expected_size} bytes")
    if len(out) != expected_size:
        raise LZFError(f"LZF stream decodes to {len(out)} bytes, expected {expected_size}")
    return bytes(out)
