"""The pure numeric core: numpy in, numpy out; no I/O, no asyncio, no globals."""
