"""Warp beside torch: initialization, dtypes, streams, kernel launches and CUDA-graph capture.

Everything gnwarp launches goes through here: a ``Launcher`` runs Warp kernels on the device and
current torch stream of a tensor, with zero-copy Warp views of torch tensors as arguments, so
Warp work interleaves with torch's and a ``torch.cuda.graph`` capture records it (``cuda_graph``).
"""
from __future__ import annotations

import contextlib
import ctypes
import functools
import gc
import os
import sys
import tempfile

import torch
import warp as wp

__all__ = ["warp", "cuda_available", "resolve_device", "WP_DTYPE", "warp_stream", "cuda_graph", "Graphed", "replay_cached",
           "Launcher", "registers_generators", "default_generator", "capture_problem", "vjp"]


@functools.lru_cache(maxsize=None)
def warp():
    """The ``warp`` module, initialized once, its banner and module-load lines silenced (Warp
    1.19 logs them at info level; warnings and errors still show)."""
    wp.config.log_level = wp.LOG_WARNING
    if _cuda_driver_loads():
        wp.init()
    else:  # a CPU machine: Warp's C code warns that the driver is missing, which is expected here
        with _stderr_without(_NO_DRIVER):
            wp.init()
    return wp


# what Warp's native init prints (to fd 2, from C) when it cannot load the CUDA driver
_NO_DRIVER = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"


def _cuda_driver_loads() -> bool:
    """Whether the CUDA driver library loads, the way Warp looks for it (True where it cannot be
    told: other platforms are left to Warp)."""
    names = {"linux": ("libcuda.so", "libcuda.so.1"), "win32": ("nvcuda.dll",)}.get(
        "linux" if sys.platform.startswith("linux") else sys.platform)
    if names is None:
        return True
    for name in names:
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            pass
    return False


@contextlib.contextmanager
def _stderr_without(line: str):
    """File descriptor 2 captured while the block runs (C code writes there, not to
    ``sys.stderr``); afterwards everything it got is written to stderr except lines containing
    ``line``, so other warnings and errors still show."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no file descriptor 2 to capture: run as is
        yield
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            try:
                sys.stderr.flush()
            except (OSError, ValueError):
                pass
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            kept = [x for x in tmp.read().decode(errors="replace").splitlines(keepends=True) if line not in x]
            if kept:
                sys.stderr.write("".join(kept))
                sys.stderr.flush()


def cuda_available() -> bool:
    """Whether Warp sees a CUDA device."""
    try:
        return warp().get_cuda_device_count() > 0
    except Exception:  # noqa: BLE001 - no usable Warp CUDA runtime means no CUDA here
        return False


def vjp(output: torch.Tensor, inputs, grad: torch.Tensor) -> tuple:
    """``torch.autograd.grad(output, inputs, grad, allow_unused=True)``: the gradients (a tuple, None
    for an input ``output`` does not depend on) of ``output`` weighted by ``grad`` (same shape).
    Calls torch's autograd engine the way ``torch.autograd.grad`` does, without its shape check,
    whose first call imports sympy (about a second of a fresh process's first backward). The
    engine entry is a private torch name: where it is missing or takes other arguments, the
    public call runs (it raises any error of the backward itself again)."""
    if grad.shape != output.shape:
        raise ValueError(f"grad must have the output's shape {tuple(output.shape)}, got {tuple(grad.shape)}")
    inputs = tuple(inputs)
    run = getattr(torch.autograd.graph, "_engine_run_backward", None)
    if run is not None:
        try:
            return run((output,), (grad,), False, False, inputs, True, accumulate_grad=False)
        except TypeError:   # another torch's signature
            pass
    return torch.autograd.grad(output, inputs, grad, allow_unused=True)


def resolve_device(device: str | torch.device | None = "auto") -> torch.device:
    """``"auto"`` (or None): CUDA when torch sees it, else the CPU; anything else as torch reads it,
    refused (``ValueError``) where it cannot run here: a misspelt device, CUDA where torch sees
    none, a GPU index beyond those visible."""
    if device is None or device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        d = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"device {device!r} is not a device (cpu, cuda, cuda:N or auto): {e}") from None
    if d.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {device!r} asked for, but torch sees no CUDA device here (a CPU-only torch "
                             "build, or no GPU visible): use cpu or auto")
        if d.index is not None and d.index >= torch.cuda.device_count():
            raise ValueError(f"device {device!r}: only {torch.cuda.device_count()} CUDA device(s) visible")
    elif d.type not in ("cpu", "meta"):
        raise ValueError(f"device {device!r}: gnwarp runs on cpu or cuda")
    return d


# torch dtype -> Warp dtype
WP_DTYPE = {torch.float32: wp.float32, torch.float64: wp.float64, torch.float16: wp.float16,
            torch.bfloat16: wp.bfloat16, torch.int32: wp.int32}

_STREAMS: dict[int, object] = {}


def warp_stream(torch_stream: torch.cuda.Stream):
    """The Warp stream wrapping a torch CUDA stream (made once per stream, then cached)."""
    key = torch_stream.cuda_stream
    s = _STREAMS.get(key)
    if s is None:
        warp()
        s = _STREAMS[key] = wp.stream_from_torch(torch_stream)
    return s


@contextlib.contextmanager
def cuda_graph(graph: torch.cuda.CUDAGraph, stream: torch.cuda.Stream | None = None, **kwargs):
    """``torch.cuda.graph(graph, stream)`` that Warp knows about: gnwarp launches inside are
    recorded into ``graph`` (Warp also keeps their modules loaded while the graph lives).

    Run the step once before (on ``stream``): kernels compile and load on first use, which must
    not happen during capture. Usage::

        s = torch.cuda.Stream(); s.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(s):
            step()                      # warm-up
        torch.cuda.current_stream().wait_stream(s)
        g = torch.cuda.CUDAGraph()
        with gnwarp.cuda_graph(g, s):
            step()
        g.replay()
    """
    stream = stream if stream is not None else torch.cuda.Stream()
    # No garbage collection inside the capture (torch.cuda.graph collects just before it): a
    # collection there could run the destructors of earlier graphs or buffers held in reference
    # cycles, whose CUDA calls are not allowed while a stream captures.
    collecting = gc.isenabled()
    gc.disable()
    try:
        with wp.ScopedStream(warp_stream(stream)), torch.cuda.graph(graph, stream=stream, **kwargs):
            wp.capture_begin(force_module_load=False, external=True)
            try:
                yield
            finally:
                wp.capture_end()
    finally:
        if collecting:
            gc.enable()


class Graphed:
    """``fn()`` replayed from a CUDA graph. The first ``warmup`` calls run it eagerly on a side
    stream (kernels compile and load, one-off tables are made); the next records it and replays
    the record; every later call replays it. ``fn`` must read and write only tensors that live
    from one call to the next (allocated before, or made inside and kept by the graph's pool),
    and nothing in it may sync with the host. ``generator``: a random generator ``fn`` draws
    from other than the device's default (registered with the graph). ``prime``: run once on
    the side stream just before the recording, in place of eager calls of ``fn`` where ``fn``
    is dear (with ``warmup=0``, the first call primes, records and replays): a cheaper call
    that loads the same kernels and makes the same lazy state without changing what ``fn``
    works on. ``warmup=0`` without ``prime`` records on the first call: only for an ``fn``
    whose kernels are loaded and whose lazy state (GEMM handles, tables) is made already."""

    def __init__(self, fn, warmup: int = 1, generator: torch.Generator | None = None, prime=None):
        if isinstance(warmup, bool) or not isinstance(warmup, int) or warmup < 0:
            raise ValueError(f"warmup must be an integer >= 0 (eager calls before the recording), got {warmup!r}")
        self.fn, self.warmup, self.generator, self.prime = fn, warmup, generator, prime
        self.graph: torch.cuda.CUDAGraph | None = None
        self.stream = torch.cuda.Stream()

    def __call__(self) -> None:
        if self.graph is None:
            self.stream.wait_stream(torch.cuda.current_stream())
            if self.warmup > 0:
                with torch.cuda.stream(self.stream):
                    self.fn()
                torch.cuda.current_stream().wait_stream(self.stream)
                self.warmup -= 1
                return
            if self.prime is not None:
                with torch.cuda.stream(self.stream):
                    self.prime()
                self.prime = None
            graph = torch.cuda.CUDAGraph()
            if self.generator is not None:
                graph.register_generator_state(self.generator)
            with cuda_graph(graph, self.stream):
                self.fn()  # recorded, not run
            torch.cuda.current_stream().wait_stream(self.stream)
            self.graph = graph
        self.graph.replay()


# -- what a captured training step needs ----------------------------------------------------------
# Uncaptured, a training step launches tens of Warp kernels and ~100 torch ones from Python, each
# costing tens of microseconds of host time; ``Graphed`` replays the step's device work (batch
# sampling, noise, normalizer accumulation, loss, backward, clipping, the optimizer update, the
# running loss sums) as one launch. What must hold for a step to be captured (``capture_problem``
# says what does not): a CUDA device; batches of one shape (graphs of one topology per dataset);
# an optimizer whose learning rate lives on the device (``FlatAdam``, or torch's Adam made
# capturable with a tensor learning rate); a random generator the graph can replay (the device's
# default generator, or any with ``CUDAGraph.register_generator_state``).

def registers_generators() -> bool:
    """Whether this torch can replay random numbers of any generator in a CUDA graph."""
    return hasattr(torch.cuda.CUDAGraph, "register_generator_state")


def default_generator(device: torch.device) -> torch.Generator:
    """The default random generator of a CUDA device (CUDA graphs replay it by themselves)."""
    return torch.cuda.default_generators[device.index if device.index is not None else torch.cuda.current_device()]


def capture_problem(device: torch.device, static_shapes: bool, generator: torch.Generator) -> str | None:
    """None if a training step on ``device`` can be captured, else why not."""
    if device.type != "cuda":
        return "capture needs a CUDA device"
    if not static_shapes:
        return "the batches' graphs vary in size (several topologies in one dataset)"
    if generator is not default_generator(device) and not registers_generators():
        return "this torch cannot replay a non-default random generator in a CUDA graph"
    return None


def replay_cached(cache: dict, key, inputs: tuple, run, keep=None, limit: int = 4):
    """``run(*buffers)`` replayed from a CUDA graph kept in ``cache`` under ``key``: on a miss,
    ``inputs`` (CUDA tensors) are copied into new buffers and ``run`` is warmed up and captured
    (``Graphed``); each call copies ``inputs`` into the buffers and replays. At most ``limit``
    graphs stay in ``cache`` (each holds its own memory; the oldest goes first). ``keep``: what
    the entry holds alive (e.g. an object whose id the key names). Returns the captured run's
    outputs: the graph's own tensors, which the next replay overwrites (clone what must outlive
    it)."""
    entry = cache.get(key)
    if entry is None:
        with torch.cuda.device(inputs[0].device):
            bufs = tuple(x.clone() for x in inputs)
            out = {}
            graphed = Graphed(lambda: out.__setitem__("result", run(*bufs)))
            graphed()                     # warm-up: kernels compiled, one-off tables and indexes made
        while len(cache) >= limit:
            cache.pop(next(iter(cache)))
        entry = cache[key] = (graphed, bufs, out, keep)
    graphed, bufs, out, _ = entry
    for b, x in zip(bufs, inputs):
        b.copy_(x)
    with torch.cuda.device(bufs[0].device):
        graphed()
    return out["result"]


_PLACEHOLDERS: dict[tuple, object] = {}


class Launcher:
    """Launches Warp kernels on the device and current torch stream of ``like`` (a tensor)."""

    def __init__(self, like: torch.Tensor):
        warp()  # initialized once
        self.torch_device = like.device
        self.device = wp.device_from_torch(like.device)
        self.stream = warp_stream(torch.cuda.current_stream(like.device)) if like.device.type == "cuda" else None

    @property
    def is_cuda(self) -> bool:
        return self.stream is not None

    def placeholder(self, dtype, ndim: int):
        """Zero-size array for the argument of an input a kernel was built without (never read):
        a torch tensor for a torch ``dtype``, a Warp array for a Warp one (vector types too);
        made once per device, dtype and rank."""
        key = (self.torch_device, dtype, ndim)
        t = _PLACEHOLDERS.get(key)
        if t is None:
            shape = (0,) * ndim
            t = _PLACEHOLDERS[key] = (torch.empty(shape, dtype=dtype, device=self.torch_device)
                                      if isinstance(dtype, torch.dtype) else wp.empty(shape, dtype=dtype, device=self.device))
        return t

    @staticmethod
    def array(a):
        """Zero-copy Warp view of a torch tensor (other arguments pass through)."""
        if isinstance(a, torch.Tensor):
            return wp.from_torch(a, dtype=WP_DTYPE.get(a.dtype), requires_grad=False, return_ctype=True)
        return a

    @staticmethod
    def outputs_from(kernel) -> int:
        """Index of ``kernel``'s first output: its parameters named ``*_out`` come last (the
        convention of ``gnwarp.kernels``); counted once per kernel and kept on it (a launch is hot)."""
        k = getattr(kernel, "gnwarp_first_output", None)
        if k is None:
            k = sum(not a.label.endswith("_out") for a in kernel.adj.args)
            kernel.gnwarp_first_output = k
        return k

    def __call__(self, kernel, dim: int, *args):
        """Launch ``kernel`` over ``dim`` threads (nothing when ``dim`` is 0) with ``args`` in the
        order of its parameters (inputs, then outputs)."""
        if dim == 0:
            return
        args = [self.array(a) for a in args]
        k = self.outputs_from(kernel)
        wp.launch(kernel, dim=dim, inputs=args[:k], outputs=args[k:], device=self.device, stream=self.stream)

    def tiled(self, kernel, blocks: int, block_dim: int, *args, adjoint: list | None = None):
        """Launch a tile kernel over ``blocks`` blocks of ``block_dim`` threads on CUDA (one thread a
        block on the CPU); ``adjoint``: the adjoint launch, with these gradient arrays (None for
        integer arguments) in the order of ``args``."""
        if blocks == 0:
            return
        k = self.outputs_from(kernel)
        kw = {}
        if adjoint is not None:
            adj = [None if a is None else self.array(a) for a in adjoint]
            kw = dict(adjoint=True, adj_inputs=adj[:k], adj_outputs=adj[k:])
        args = [self.array(a) for a in args]
        wp.launch_tiled(kernel, dim=[blocks], inputs=args[:k], outputs=args[k:], device=self.device,
                        stream=self.stream, block_dim=block_dim if self.is_cuda else 1, **kw)
