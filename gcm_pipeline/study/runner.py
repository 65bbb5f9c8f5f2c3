"""Where placements run: Ray actors (local or on a cluster), or in this process.

:class:`RayExecutor` starts Ray on this machine (``ray.init`` with ``workers``
CPUs, no dashboard, usage statistics off) or joins
an existing cluster (``address``), creates one
:class:`~gcm_pipeline.study.worker.PlacementWorker` actor per worker (each
builds its robot, seed library and collision geometry once) and streams
placements to them, two in flight per actor so none waits for the driver.
Results come back as NumPy arrays in the order they finish. A worker that
dies (killed, out of memory, node lost) is replaced and its placement is tried
once more; a second loss is recorded as the placement's error.

:class:`InlineExecutor` runs the same worker class in this process, one
placement after the other (the reference for Ray's overhead).

``ray`` is imported only here, when a study runs: ``import gcm_pipeline``
does not load it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Iterable, Iterator
from typing import Any
from urllib.parse import urlsplit

from gcm_pipeline import interrupts
from gcm_pipeline.errors import GcmError
from gcm_pipeline.progress import note
from gcm_pipeline.study.worker import PlacementWorker

__all__ = [
    "EngineError",
    "Executor",
    "InlineExecutor",
    "RayExecutor",
    "check_local_workers",
    "probe_address",
    "ray_version",
]

log = logging.getLogger(__name__)

#: Placements queued per actor beyond the one it runs.
_IN_FLIGHT = 2


class EngineError(GcmError):
    """Ray cannot be started or reached (``--address``), or has too few CPUs."""


class Executor:
    """Runs jobs ``{"id", "config"}`` and yields worker results as they finish."""

    name = "executor"
    workers = 1

    def info(self) -> dict[str, Any]:
        """What ran the study (``summary.json``'s ``engine``)."""
        return {"name": self.name, "workers": self.workers}

    def run(self, jobs: Iterable[dict[str, Any]]) -> Iterator[dict[str, Any]]:
        """Yield one result per job (see :meth:`PlacementWorker.run`)."""
        raise NotImplementedError

    def close(self) -> None:
        """Stop the workers (and Ray, when this executor started it)."""


class InlineExecutor(Executor):
    """Placements in this process, one after the other, on one :class:`PlacementWorker`.

    Args:
        warm: The base config dict (robot, seed library and geometry built now).
    """

    name = "inline"

    def __init__(self, warm: dict[str, Any] | None = None) -> None:
        t0 = time.perf_counter()
        self.worker = PlacementWorker(warm)
        self.startup_s = time.perf_counter() - t0

    def info(self) -> dict[str, Any]:
        """``{"name": "inline", "workers": 1, "startup_s"}``."""
        return {"name": self.name, "workers": 1, "startup_s": round(self.startup_s, 3)}

    def run(self, jobs: Iterable[dict[str, Any]]) -> Iterator[dict[str, Any]]:
        """Run the jobs one by one."""
        for job in jobs:
            yield self.worker.run(job)


def probe_address(address: str, timeout: float = 5.0) -> None:
    """Check that a Ray cluster answers at ``address`` before Ray tries (and retries) it.

    ``auto`` is left to Ray. ``HOST:PORT`` must be a Ray head's GCS: it is
    asked for its cluster id (the gRPC call ``NodeInfoGcsService/GetClusterId``
    every Ray client makes first) over one HTTP/2 connection;
    ``ray://HOST:PORT`` must answer as an HTTP/2 (gRPC) server. Each step
    has ``timeout`` seconds, so a port where something else listens (a web
    server, a silent socket) is an error within seconds instead of
    ``ray.init`` retrying for minutes with the signals held. Ctrl-C and
    SIGTERM stop the probe at once.

    Raises:
        EngineError: ``--address ...: ...`` with the reason.
    """
    if address == "auto":
        return
    try:
        url = urlsplit(address if "://" in address else f"tcp://{address}")
        host, port = url.hostname, url.port
    except ValueError:  # an unbalanced IPv6 bracket, a port that is no number
        host, port, url = None, None, None
    if url is None or not host or port is None or url.scheme not in ("tcp", "ray"):
        raise EngineError(
            f"--address {address!r}: expected HOST:PORT (a Ray head's GCS address, e.g. "
            "10.0.0.5:6379 or [::1]:6379), ray://HOST:PORT or auto"
        )
    _probe(address, host, port, timeout, gcs=url.scheme == "tcp")
    if url.scheme == "ray":
        return
    # Ray replaces a loopback host by this machine's address before it connects
    # (and then retries for minutes): check the address it will really use
    try:
        used = _import_ray()._private.services.canonicalize_bootstrap_address(f"{host}:{port}")
    except Exception:  # a private helper of Ray: skip the check when it moved
        return
    try:
        used_url = urlsplit(f"tcp://{used}") if used else None
        used_host, used_port = (used_url.hostname, used_url.port) if used_url else (None, None)
    except ValueError:
        return
    if used_host and used_host != host:
        _probe(address, used_host, used_port or port, timeout, gcs=True, rewritten=used)


#: The gRPC method every Ray client calls first on the GCS.
_GCS_METHOD = "/ray.rpc.NodeInfoGcsService/GetClusterId"


def _probe(
    address: str,
    host: str,
    port: int,
    timeout: float,
    *,
    gcs: bool,
    rewritten: str | None = None,
) -> None:
    def fail(reason: str) -> EngineError:
        if rewritten is not None:
            return EngineError(
                f"--address {address}: Ray would connect to {rewritten} (this machine's "
                f"address), where no Ray cluster answers ({reason}); start the head with "
                "--node-ip-address of that address, or set RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 "
                "to keep Ray on the loopback address"
            )
        return EngineError(
            f"--address {address}: no Ray cluster answers there ({reason}); start one with "
            "'ray start --head' or drop --address to run on this machine"
        )

    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except OSError as exc:
        raise fail(exc.strerror or type(exc).__name__) from None
    with sock:
        try:
            authority = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
            reason = _grpc_call(sock, authority, timeout, gcs=gcs)
        except TimeoutError:
            reason = f"something accepts connections but sent no HTTP/2 answer within {timeout:g} s"
        except OSError as exc:
            reason = f"the connection failed: {exc.strerror or type(exc).__name__}"
    if reason:
        raise fail(reason)


def _grpc_call(sock: socket.socket, authority: str, timeout: float, *, gcs: bool) -> str:
    """Speak HTTP/2 to ``sock``; with ``gcs``, call GetClusterId. Returns '' or why not Ray."""
    deadline = time.monotonic() + timeout

    def frame(kind: int, flags: int, stream: int, payload: bytes = b"") -> bytes:
        head = len(payload).to_bytes(3, "big") + bytes((kind, flags))
        return head + stream.to_bytes(4, "big") + payload

    def recv(n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError
            sock.settimeout(left)
            chunk = sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionResetError(0, "closed by the server")
            buf += chunk
        return buf

    out = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + frame(0x4, 0, 0)
    if gcs:
        fields = {
            ":method": "POST",
            ":scheme": "http",
            ":path": _GCS_METHOD,
            ":authority": authority,
            "content-type": "application/grpc",
            "te": "trailers",
        }
        block = b"".join(_hpack_literal(k, v) for k, v in fields.items())
        out += frame(0x1, 0x4, 1, block)  # HEADERS, END_HEADERS
        out += frame(0x0, 0x1, 1, b"\x00\x00\x00\x00\x00")  # an empty request, END_STREAM
    sock.settimeout(max(deadline - time.monotonic(), 0.001))
    sock.sendall(out)
    first = recv(9)
    if first.startswith(b"HTTP/"):
        return "an HTTP/1 server answers there, not a Ray cluster's GCS"
    if first[3] != 0x4:  # a server's HTTP/2 preface is a SETTINGS frame
        return "the server there does not speak HTTP/2 (gRPC)"
    data = b""
    header = first
    while True:
        size, kind, flags = int.from_bytes(header[:3], "big"), header[3], header[4]
        stream = int.from_bytes(header[5:9], "big") & 0x7FFFFFFF
        if size > 1 << 20:
            return "the server there sent an HTTP/2 frame of more than 1 MiB"
        payload = recv(size) if size else b""
        if kind == 0x4 and not flags & 0x1:
            sock.sendall(frame(0x4, 0x1, 0))  # acknowledge the server's settings
            if not gcs:
                return ""
        elif kind == 0x6 and not flags & 0x1:  # PING: answer it
            sock.sendall(frame(0x6, 0x1, 0, payload))
        elif kind == 0x7:
            return "the HTTP/2 server there closed the connection (GOAWAY), it is not Ray's GCS"
        elif kind == 0x3 and stream == 1:
            return f"the HTTP/2 server there refused {_GCS_METHOD}, it is not Ray's GCS"
        elif kind == 0x0 and stream == 1:
            if flags & 0x8 and payload:  # PADDED
                payload = payload[1 : len(payload) - payload[0]]
            data += payload
            if len(data) >= 5:
                size = int.from_bytes(data[1:5], "big")
                if size > 1 << 20:  # a cluster id is 28 bytes
                    return f"the server there answered {_GCS_METHOD} with {size:,} bytes"
                if len(data) >= 5 + size:
                    return _cluster_id_reply(data[5 : 5 + size])
        if kind in (0x0, 0x1) and stream == 1 and flags & 0x1:  # END_STREAM with no reply
            # a gRPC status only (Ray's GCS with token authentication says 16,
            # UNAUTHENTICATED); 12, UNIMPLEMENTED: a gRPC server, but not Ray's GCS
            if kind == 0x1 and _literal_value(payload, b"grpc-status") not in (b"12", None):
                return ""
            return f"the gRPC server there has no {_GCS_METHOD}, it is not Ray's GCS"
        header = recv(9)


def _cluster_id_reply(message: bytes) -> str:
    """'' when ``message`` is a GCS's GetClusterId reply with a cluster id, else why not."""
    try:
        reply_type = _import_ray().core.generated.gcs_service_pb2.GetClusterIdReply
    except (EngineError, AttributeError):  # Ray moved its messages: an answer is good enough
        return ""
    try:
        reply = reply_type.FromString(message)
    except Exception:
        return f"the gRPC server there answered {_GCS_METHOD} with something else"
    if reply.status.code != 0 or not reply.cluster_id:
        return f"the gRPC server there gave no cluster id (status {reply.status.code})"
    return ""


def _literal_value(block: bytes, name: bytes) -> bytes | None:
    """The value after the literal header ``name`` in an HPACK block (not Huffman-coded), or None.

    Enough to read a status a gRPC server sends in plain text; a block that
    codes it otherwise gives None.
    """
    at = block.find(bytes((len(name),)) + name)
    if at < 0 or at + 1 + len(name) >= len(block):
        return None
    start = at + 1 + len(name)
    size = block[start]
    if size & 0x80 or size == 0x7F:  # Huffman-coded, or a long value
        return None
    return block[start + 1 : start + 1 + size]


def _hpack_literal(name: str, value: str) -> bytes:
    """An HPACK header field, literal without indexing, no Huffman coding (RFC 7541 6.2.2)."""
    out = b"\x00"
    for text in (name, value):
        raw = text.encode("utf-8")
        out += _hpack_int(len(raw)) + raw
    return out


def _hpack_int(n: int) -> bytes:
    """An HPACK integer with a 7-bit prefix (the string length, H bit 0)."""
    if n < 127:
        return bytes((n,))
    out = [127]
    n -= 127
    while n >= 128:
        out.append(n % 128 + 128)
        n //= 128
    out.append(n)
    return bytes(out)


@contextlib.contextmanager
def _caller_signal_handlers() -> Iterator[None]:
    """Keep the caller's SIGTERM, SIGHUP and SIGINT handlers across ``ray.init``/``shutdown``.

    ``ray.init`` sets its own SIGTERM handler (exit at once with status 15,
    Ray's core worker printing a stack), which would replace ``gcm study``'s
    (stop the workers, keep what finished, exit 143 like Ctrl-C). A handler the
    caller set (a Python function, or ignore) is put back afterwards; where
    the caller had none, Ray's stays (it stops the Ray processes it started).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    sigs = [getattr(signal, n) for n in ("SIGTERM", "SIGHUP", "SIGINT") if hasattr(signal, n)]
    saved = {sig: signal.getsignal(sig) for sig in sigs}
    try:
        yield
    finally:
        for sig, handler in saved.items():
            if callable(handler) or handler == signal.SIG_IGN:
                signal.signal(sig, handler)


#: Seconds an interrupt waits for ``ray.init`` joining a cluster before it cuts it.
_JOIN_GRACE_S = 10.0


@contextlib.contextmanager
def _uninterrupted(ray: Any, grace: float | None = None) -> Iterator[list[int]]:
    """Run ``ray.init`` whole: Ctrl-C, SIGTERM and SIGHUP are held until it returns.

    With ``grace``, a held interrupt is raised after that many seconds all the
    same (joining a cluster: nothing local to leave running, and a head that
    answers the probe but then never the driver must not hold SIGTERM forever).

    Cut in the middle, Ray's start-up left its dashboard and runtime-env agents
    running, and the interpreter sometimes crashed at exit (status 139). The
    signals received are yielded for the caller to raise once Ray can be
    stopped; ``ray.init`` is kept from installing its own SIGTERM handler (exit
    at once) meanwhile, and the caller's handlers are back afterwards.
    """
    utils: Any = getattr(getattr(ray, "_private", None), "utils", None)
    setter = getattr(utils, "set_sigterm_handler", None)
    with _caller_signal_handlers(), interrupts.held(grace) as got:
        # only while SIGTERM is held: else Ray's handler is what stops its processes
        patch = setter is not None and callable(signal.getsignal(signal.SIGTERM))
        if patch:
            utils.set_sigterm_handler = lambda handler: None
        try:
            yield got
        finally:
            if patch:
                utils.set_sigterm_handler = setter


def check_local_workers(workers: int | None) -> None:
    """Refuse more workers than this machine has CPUs (Ray started here, no ``--address``).

    Ray would believe in that many CPUs and start an actor for each.

    Raises:
        EngineError: ``--workers N: this machine has C CPUs; ...``.
    """
    cpus = os.cpu_count() or 1
    if workers is not None and workers > cpus:
        raise EngineError(
            f"--workers {workers}: this machine has {cpus} CPUs; use --workers {cpus} "
            "or fewer, or --address to run on a cluster"
        )


def ray_version() -> dict[str, str]:
    """``{"ray": version}`` when this process imported Ray (a study on Ray), else ``{}``."""
    ray = sys.modules.get("ray")
    return {"ray": str(ray.__version__)} if ray is not None else {}


def _import_ray() -> Any:
    """Ray, imported on first use: the study's one import of it (no usage statistics)."""
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    try:
        import ray
    except ImportError as exc:  # pragma: no cover - ray is a dependency
        raise EngineError(f"studies run on Ray, which cannot be imported: {exc}") from None
    return ray


def _starting_line(workers: int | None, address: str | None) -> str:
    """``study: starting Ray (2 workers)...`` (or joining a cluster, or Ray already running)."""
    running = sys.modules.get("ray")
    if running is not None and running.is_initialized():
        return "study: using the Ray this process runs already..."
    if address is not None:
        return f"study: joining the Ray cluster at {address}..."
    n = workers or os.cpu_count() or 1
    return f"study: starting Ray ({n} worker{'s' * (n != 1)})..."


class RayExecutor(Executor):
    """Placements on Ray actors, one :class:`PlacementWorker` per CPU used.

    Args:
        workers: Actors (one CPU each). None: every CPU of this machine, or of
            the cluster with ``address``.
        address: An existing Ray cluster (``HOST:PORT``, ``ray://HOST:PORT``,
            ``auto``); None starts Ray on this machine for this study.
        warm: The base config dict each actor builds its robot from at start.
        progress: Say on stderr that Ray starts (``study: starting Ray (2
            workers)...``) and when it is ready (``study: Ray ready in 6.2 s``,
            its workers' robots built).

    Raises:
        EngineError: The cluster cannot be reached, or it (without ``address``:
            this machine) has fewer CPUs than ``workers``.
    """

    name = "ray"

    def __init__(
        self,
        workers: int | None = None,
        address: str | None = None,
        warm: dict[str, Any] | None = None,
        *,
        progress: bool = False,
    ) -> None:
        if workers is not None and workers < 1:
            raise EngineError(f"--workers must be >= 1, got {workers}")
        t0 = time.perf_counter()
        note(_starting_line(workers, address), enabled=progress)
        ray = self.ray = _import_ray()
        if address is not None:
            probe_address(address)
        self.started = False
        self.address = address
        got: list[int] = []  # interrupts held while Ray started
        if ray.is_initialized():
            self.mode = "existing"
        elif address is None:
            check_local_workers(workers)
            n = workers or os.cpu_count() or 1
            try:
                with _uninterrupted(ray) as got:
                    ray.init(
                        address="local",
                        num_cpus=n,
                        include_dashboard=False,
                        log_to_driver=False,
                        logging_level=logging.ERROR,
                        object_store_memory=256 * 1024**2,
                    )
            except Exception as exc:
                raise EngineError(f"cannot start Ray on this machine: {exc}") from None
            self.started = True
            self.mode = "local"
        else:
            try:
                with _uninterrupted(ray, _JOIN_GRACE_S) as got:
                    ray.init(address=address, log_to_driver=False, logging_level=logging.ERROR)
            except Exception as exc:
                if interrupts.interrupt_cause(exc) is not None:  # cut after the grace: an interrupt
                    raise
                first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                raise EngineError(
                    f"--address {address}: cannot join the cluster: {first}"
                ) from None
            self.started = True
            self.mode = "cluster"
        if got:  # an interrupt during start-up: Ray is up, so it stops cleanly
            self.close()
            interrupts.release(got)
        try:
            cpus = int(ray.cluster_resources().get("CPU", 0))
            self.workers = workers or max(cpus, 1)
            if self.workers > cpus:
                raise EngineError(
                    f"--workers {self.workers}: the Ray cluster has {cpus} CPUs; "
                    f"use --workers {max(cpus, 1)} or fewer"
                )
            self.nodes = sum(1 for n in ray.nodes() if n.get("Alive"))
            self._actor_cls = ray.remote(num_cpus=1, max_restarts=0)(PlacementWorker)
            self._warm = warm
            self.actors = [self._new_actor() for _ in range(self.workers)]
            self.where = ray.get([a.ready.remote() for a in self.actors])
        except BaseException:
            self.close()
            raise
        self.startup_s = time.perf_counter() - t0
        note(
            f"study: Ray ready in {self.startup_s:.1f} s ({self.workers} worker"
            f"{'s' * (self.workers != 1)} on {self.nodes} node{'s' * (self.nodes != 1)})",
            enabled=progress,
        )

    def _new_actor(self) -> Any:
        return self._actor_cls.remote(self._warm)

    def info(self) -> dict[str, Any]:
        """Name, Ray version, mode (local / cluster / existing), workers, nodes, start-up time."""
        return {
            "name": "ray",
            "version": self.ray.__version__,
            "mode": self.mode,
            "address": self.address,
            "workers": self.workers,
            "nodes": self.nodes,
            "worker_nodes": sorted({w["node"] for w in self.where}),
            "startup_s": round(self.startup_s, 3),
        }

    def run(self, jobs: Iterable[dict[str, Any]]) -> Iterator[dict[str, Any]]:
        """Stream the jobs over the actors; yield results as they finish."""
        ray = self.ray
        RayActorError, RayError = ray.exceptions.RayActorError, ray.exceptions.RayError

        queue = iter(jobs)
        pending: dict[Any, tuple[int, int, dict[str, Any]]] = {}
        load = [0] * len(self.actors)
        generation = [0] * len(self.actors)
        retried: set[int] = set()
        requeue: list[dict[str, Any]] = []
        exhausted = False

        def next_job() -> dict[str, Any] | None:
            nonlocal exhausted
            if requeue:
                return requeue.pop()
            if exhausted:
                return None
            job = next(queue, None)
            exhausted = job is None
            return job

        while True:
            for k in range(len(self.actors)):
                while load[k] < _IN_FLIGHT:
                    job = next_job()
                    if job is None:
                        break
                    pending[self.actors[k].run.remote(job)] = (k, generation[k], job)
                    load[k] += 1
            if not pending:
                return
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
            for ref in ready:
                k, gen, job = pending.pop(ref)
                if gen == generation[k]:
                    load[k] -= 1
                try:
                    result = ray.get(ref)
                except RayActorError as exc:
                    if gen == generation[k]:  # the first loss seen of this actor
                        log.warning("study: worker %d died (%s); starting a new one", k, exc)
                        self._kill(self.actors[k])
                        self.actors[k] = self._new_actor()
                        generation[k] += 1
                        load[k] = 0
                    if job["id"] in retried:
                        result = _failure(job, f"worker died twice: {_first_line(exc)}")
                    else:
                        retried.add(job["id"])
                        requeue.append(job)
                        continue
                except RayError as exc:
                    result = _failure(job, f"{type(exc).__name__}: {_first_line(exc)}")
                yield result

    def _kill(self, actor: Any) -> None:
        try:
            self.ray.kill(actor, no_restart=True)
        except Exception:  # already gone
            pass

    def close(self) -> None:
        """Kill the actors; shut Ray down when this executor started or joined it."""
        ray = self.ray
        for actor in getattr(self, "actors", []):
            self._kill(actor)
        self.actors = []
        if self.started and ray.is_initialized():
            # Ray's shutdown leaves its own native SIGTERM handler behind (the process
            # would die silently on it): the caller's handlers are put back
            with _caller_signal_handlers():
                ray.shutdown()
        self.started = False


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return " ".join(text.splitlines()[0].split()) if text else type(exc).__name__


def _failure(job: dict[str, Any], error: str) -> dict[str, Any]:
    return {"id": int(job["id"]), "node": "", "error": error[:2000], "time_s": float("nan")}
