"""The server side of openpi's policy-server WebSocket protocol (see ``openpi_client.py`` for the wire format):
serve one of our policies so that openpi clients, or ours, can query it. ``sc3 serve-policy`` is
``commands/serve_policy.py``.
"""
from __future__ import annotations

import hmac
import logging
import threading
import time
import traceback
from http import HTTPStatus
from typing import Any, Mapping

import msgpack
import numpy as np
import websockets
import websockets.exceptions
import websockets.sync.server
from websockets.frames import CloseCode

from sc3_jax.policies import msgpack_numpy
from sc3_jax.policies.base import HostPolicy, JaxAsHost, JaxPolicy, as_host
from sc3_jax.policies.openpi_mappings import ObsMapping, get_mapping
from sc3_jax.core.validate import mask_paths

__all__ = ["PolicyServer", "serve", "serve_until_interrupted", "MAX_MESSAGE_BYTES", "API_KEY_ENV"]

logger = logging.getLogger(__name__)

MAX_MESSAGE_BYTES = 8 * 2**20  # an observation of four 480x640 cameras is 3.7 MB
API_KEY_ENV = "SC3_POLICY_API_KEY"  # where `sc3 serve-policy` reads its key (a command-line value shows in `ps`)


class ShapeError(ValueError):
    """An observation whose keys or array shapes differ from the first one its connection had answered."""


class ObservationError(ValueError):
    """An observation this server refuses before its policy sees it (non-finite numbers, a state of another size)."""


class PolicyError(RuntimeError):
    """The policy could not take an observation (the client is told which, not the library's internals)."""


MAX_VALUES = 1 << 16  # plain msgpack values (list items, map entries) one decoded message may hold; arrays are bytes
MAX_CONNECTIONS = 8  # open connections at once: with max_queue=2, memory stays near 3 x max_size per connection
MAX_PROGRAMS = 8  # observation shapes a JAX policy keeps compiled; one more clears them (recompiled as they return)
IDLE_SECONDS = 120.0  # a connection silent this long is closed (its slot freed); our client reconnects on its own


def decode(msg: bytes, budget: int = MAX_VALUES) -> Any:
    """A message as ``msgpack_numpy.unpackb`` decodes it, refused (ValueError) once it holds more than ``budget``
    plain values: an image sent as nested lists would otherwise decode to tens of bytes of Python objects per byte
    sent, past any message-size bound. Counted while decoding, so the refusal comes before the memory is taken."""
    left = [budget]

    def spend(n: int) -> None:
        left[0] -= n
        if left[0] < 0:
            raise ValueError(f"the observation holds more than {budget} list items or map entries: send arrays as "
                             "numpy arrays (openpi's msgpack_numpy)")

    def as_list(items):
        spend(len(items))
        return items

    def as_map(obj):
        spend(len(obj))
        return msgpack_numpy.unpack_array(obj)
    return msgpack.unpackb(msg, object_hook=as_map, list_hook=as_list, max_array_len=budget, max_map_len=budget)


def _list_shape(v: list) -> tuple:
    """The nested lengths of a list (an image sent as lists of lists), "ragged" where they differ."""
    inner = {_list_shape(x) if isinstance(x, list) else () for x in v}
    return (len(v), *inner.pop()) if len(inner) == 1 else (len(v), "ragged")


def signature(obs: Mapping, prefix: str = "") -> dict[str, tuple]:
    """Key -> (shape, dtype) of every array of a (nested) observation, whatever container carried it (a numpy array
    or nested lists); other values (a prompt, sent or not) are free. Two observations with one signature run one
    compiled program."""
    out: dict[str, tuple] = {}
    for k, v in obs.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(signature(v, key + "/"))
        elif isinstance(v, np.ndarray):
            out[key] = (tuple(v.shape), v.dtype.str)
        elif isinstance(v, list):
            out[key] = (_list_shape(v), "list")
    return out


def check_finite(obs: Mapping, prefix: str = "") -> None:
    """ObservationError naming the first array (of a nested observation) holding NaN or inf: a policy would answer
    it with NaN actions, which a client would execute or average in."""
    for k, v in obs.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            check_finite(v, key + "/")
        elif isinstance(v, (np.ndarray, np.generic)) and v.dtype.kind in "fc" and not np.all(np.isfinite(v)):
            raise ObservationError(f"observation {key} holds NaN or inf: send finite numbers")
        elif isinstance(v, float) and not np.isfinite(v):
            raise ObservationError(f"observation {key} is {v}: send finite numbers")


def describe(sig: Mapping[str, tuple]) -> str:
    """An observation's signature as a client reads it: ``images [4, 4, 3] |u1, state [2] <f4``."""
    return ", ".join(f"{k} {list(shape)} {dtype}" for k, (shape, dtype) in sorted(sig.items()))


def _peer(ws) -> str:
    """The client's address as the log names it (host:port)."""
    addr = getattr(ws, "remote_address", None)
    return f"{addr[0]}:{addr[1]}" if isinstance(addr, tuple) and len(addr) >= 2 else "a client"


def one_line(e: BaseException) -> str:
    """What a client is told of an error: its type and first line, every path masked (``validate.mask_paths``: rooted,
    ``./``, ``../``, ``~`` and relative file names), so the server's layout stays in its log with the traceback."""
    first = mask_paths((str(e).strip().splitlines() or [""])[0])[:300]
    return f"{type(e).__name__}: {first}" if first else type(e).__name__


class PolicyServer:
    """Serve one of our policies (a :class:`JaxPolicy`, wrapped with ``as_host``, or any :class:`HostPolicy`) over
    openpi's protocol, so openpi clients (``openpi_client.WebsocketClientPolicy``) or ours can query it.

    Requests are our observation dict (``mapping=None``) or a family's observation, mapped back with
    ``mapping.from_family``; the reply is ``{"actions": ..., "server_timing": {"infer_ms", "prev_total_ms"}}`` with
    actions mapped by ``mapping.actions_to_family``. A HostPolicy whose ``infer`` returns a dict is passed through
    (openpi-style policies). An exception inside the policy sends the traceback as a text frame and closes the
    connection with 1011, like openpi. ``GET /healthz`` -> 200 ``OK`` and, on the lines after, what the server
    expects and the shapes its connections send (:meth:`health`). With ``api_key`` set, WebSocket connections
    must carry ``Authorization: Api-Key <key>`` (else 401). Inference is serialised with a lock (one policy, many
    connections). ``port=0`` binds a free port (see ``.port``). Use ``start()`` for a background thread and
    ``shutdown()`` to stop, or ``serve_forever()`` to block.

    Safe to expose: it binds 127.0.0.1 unless told otherwise; at most ``max_connections`` are served at once (a
    further one gets 503) and one silent for ``idle_seconds`` is closed, freeing its slot; a message over
    ``max_message_bytes`` closes its connection (1009) before it is read, and one of more than ``MAX_VALUES`` plain
    values (an image as nested lists) is refused while it is decoded; an observation holding NaN or inf, or a state
    of another size than the policy declares, is refused before the policy sees it, and non-finite actions never
    leave; each connection is served on its own terms: the first observation the policy answers on it fixes that
    connection's keys and array shapes, whatever container carried them, and another on it is refused (a refused one
    fixes nothing), while other connections keep theirs -- one client's odd shapes lock no other out; a JAX policy
    keeps at most ``MAX_PROGRAMS`` shapes compiled. An error reaches the client as one line without paths or the
    library's internals (a JAX policy's shape error names the observation's shapes, not XLA's); the server's log
    has one line per refusal (the traceback of a policy's own failure at DEBUG).
    """

    def __init__(self, policy: JaxPolicy | HostPolicy, host: str = "127.0.0.1", port: int = 8000,
                 metadata: Mapping[str, Any] | None = None, mapping: ObsMapping | str | None = None,
                 api_key: str | None = None, max_message_bytes: int = MAX_MESSAGE_BYTES,
                 max_connections: int = MAX_CONNECTIONS, idle_seconds: float = IDLE_SECONDS):
        self.policy = as_host(policy) if isinstance(policy, JaxPolicy) else policy
        if not callable(getattr(self.policy, "infer", None)):
            raise TypeError(f"{type(policy).__name__} is neither a JaxPolicy nor a HostPolicy (no .infer)")
        self.mapping = get_mapping(mapping)
        name = getattr(policy, "name", type(policy).__name__)
        if self.mapping is not None:  # a JaxPolicy (or a HostPolicy that says) knows its dims: refuse at start
            self.mapping.check_dims(action_dim=getattr(policy, "action_dim", None),
                                    state_dim=getattr(policy, "state_dim", None), who=f"policy {name!r}")
        self.api_key = api_key
        chunk = getattr(self.policy, "chunk", None)
        self.metadata = {"server": "sc3_jax", "policy": str(name), "family": self.mapping.name if self.mapping else
                         "native", **({"chunk": int(chunk)} if isinstance(chunk, int) else {}),
                         **({"action_dim": self.mapping.action_map.family_dim} if self.mapping else {}),
                         **dict(metadata or {})}
        msgpack_numpy.packb(self.metadata)  # fail now, not on the first connection
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._serving = False
        self._stopped = False
        self.shapes: dict[tuple, int] = {}  # signature -> open connections whose first answer fixed it (_open_lock)
        self._programs: set[tuple] = set()  # signatures the policy has compiled since its programs were last cleared
        self.expects = self._declared()
        self.max_connections = int(max_connections)
        self.idle_seconds = float(idle_seconds)
        self._open = 0  # connections being served (a further one is answered 503 before its upgrade)
        self._open_lock = threading.Lock()
        # max_queue: at most a few messages buffered per connection, so memory stays near max_size per client
        self._server = websockets.sync.server.serve(self._handler, host, port, compression=None,
                                                    max_size=int(max_message_bytes), max_queue=2,
                                                    process_request=self._process_request)
        self.host, self.port = self._server.socket.getsockname()[:2]

    @property
    def url(self) -> str:
        """Where a client on this machine connects (a wildcard address is reached at loopback)."""
        host = "127.0.0.1" if self.host in ("0.0.0.0", "::") else self.host
        return f"ws://{host}:{self.port}"

    @property
    def listening(self) -> str:
        """The address the server listens on, as bound (``0.0.0.0``: every interface)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    def _declared(self) -> str:
        """What this server expects of an observation, as far as it knows before any arrives."""
        if self.mapping is None:
            what = "our observation dict (images [V, H, W, 3] uint8, state [S], task [])"
        else:
            what = f"family {self.mapping.name}'s observation ({self.mapping._cameras()}, its state and prompt)"
        state = getattr(self.policy, "state_dim", None)
        return what + (f"; state [{int(state)}] (the policy's state_dim)" if state is not None else "")

    def health(self) -> str:
        """``/healthz``'s body: OK, what it expects, and the shapes its open connections send."""
        with self._open_lock:  # not the inference lock: a slow policy does not hold up the health check
            held = sorted((describe(dict(k)), n) for k, n in self.shapes.items())
        now = "; ".join(f"{d} ({n} connection{'s' * (n > 1)})" for d, n in held) or "none yet"
        return (f"OK\nexpects: {self.expects}\nshapes: each connection keeps the keys and shapes of its first "
                f"answered observation; answered now: {now}\n")

    def _process_request(self, connection: Any, request: Any) -> Any:
        if request.path == "/healthz":
            return connection.respond(HTTPStatus.OK, self.health())
        if self.api_key and not hmac.compare_digest(request.headers.get("Authorization") or "",
                                                    f"Api-Key {self.api_key}"):
            return connection.respond(HTTPStatus.UNAUTHORIZED, "missing or wrong Authorization: Api-Key header\n")
        if self._open >= self.max_connections:  # the common case, before the upgrade; _handler decides
            return connection.respond(HTTPStatus.SERVICE_UNAVAILABLE,
                                      f"this server takes {self.max_connections} connections at once\n")
        return None

    @staticmethod
    def _check_signature(sig: dict, fixed: dict | None) -> None:
        if fixed is not None and sig != fixed:  # one connection, one set of shapes (one compiled program)
            diff = sorted(k for k in sig.keys() | fixed.keys() if sig.get(k) != fixed.get(k))
            show = lambda s: f"{list(s[diff[0]][0])} {s[diff[0]][1]}" if diff[0] in s else None  # noqa: E731
            raise ShapeError(f"observation {diff[0]} is {show(sig) or 'missing'}, this connection sends "
                             f"{show(fixed) or 'no such key'} (fixed by its first answered observation; connect "
                             "again to send other shapes)")

    def _compiling(self, sig: dict) -> None:
        """Count ``sig`` among the policy's compiled programs (under the lock); past ``MAX_PROGRAMS`` a JAX policy's
        are cleared first, so clients sending ever new shapes cannot fill memory (each shape recompiles once)."""
        key = tuple(sorted(sig.items()))
        if key in self._programs:
            return
        clear = getattr(self.policy, "clear_programs", None)
        if len(self._programs) >= MAX_PROGRAMS and callable(clear):
            clear()
            self._programs.clear()
        self._programs.add(key)

    def _infer(self, obs: Any, fixed: dict | None = None) -> dict:
        """The reply to one observation; ``fixed``: the signature its connection's first answered observation fixed
        (None: none yet). A refused observation (here or by the policy) fixes nothing."""
        if not isinstance(obs, dict):
            raise TypeError(f"expected an observation dict, got {type(obs).__name__}")
        check_finite(obs)
        sig = signature(obs)
        self._check_signature(sig, fixed)
        ours = self.mapping.from_family(obs) if self.mapping is not None else obs
        want = getattr(self.policy, "state_dim", None)  # what the policy declares it reads
        state = ours.get("state") if isinstance(ours, Mapping) else None
        if want is not None and state is not None and np.shape(state) != (int(want),):
            raise ObservationError(f"observation state has shape {list(np.shape(state))}, policy "
                                   f"{self.metadata['policy']!r} reads [{int(want)}]")
        with self._lock:
            self._compiling(sig)
            try:
                out = self.policy.infer(ours)
            except (TypeError, ValueError, IndexError, KeyError) as e:
                if not isinstance(self.policy, JaxAsHost):
                    raise  # a host policy's own words (its author's), paths masked by one_line
                # inside JAX: a shape the traced policy cannot take; its message is the library's internals
                logger.error("policy %s failed on %s: %s", self.metadata["policy"], describe(sig), e)
                raise PolicyError(f"policy {self.metadata['policy']!r} cannot take this observation ({describe(sig)}"
                                  f"): check its arrays' shapes and dtypes ({type(e).__name__} in the policy)") from None
            if isinstance(out, Mapping):
                reply = dict(out)
            else:
                actions = np.asarray(out)
                if actions.dtype.kind in "fc" and not np.all(np.isfinite(actions)):
                    raise PolicyError(f"policy {self.metadata['policy']!r} answered non-finite actions")
                if self.mapping is not None:
                    actions = self.mapping.actions_to_family(actions)
                reply = {"actions": actions}
        return reply

    def _handler(self, ws: websockets.sync.server.ServerConnection) -> None:
        with self._open_lock:  # counted where a connection is served, so none is counted that never was
            full = self._open >= self.max_connections
            self._open += not full
        if full:
            ws.close(CloseCode.TRY_AGAIN_LATER, f"this server takes {self.max_connections} connections at once")
            return
        try:
            self._serve(ws)
        finally:
            with self._open_lock:
                self._open -= 1

    def _serve(self, ws: websockets.sync.server.ServerConnection) -> None:
        try:
            ws.send(msgpack_numpy.packb(self.metadata))
        except websockets.exceptions.ConnectionClosed:
            return
        fixed: list[dict] = []  # this connection's signature, once an observation of it is answered
        try:
            self._answer(ws, fixed)
        finally:
            if fixed:
                key = tuple(sorted(fixed[0].items()))
                with self._open_lock:
                    self.shapes[key] -= 1
                    if not self.shapes[key]:
                        del self.shapes[key]

    def _answer(self, ws: websockets.sync.server.ServerConnection, fixed: list[dict]) -> None:
        """Answer the connection's observations until it closes, the first answered one fixing ``fixed``."""
        prev_total_ms = None
        while True:
            try:
                msg = ws.recv(timeout=self.idle_seconds)
            except websockets.exceptions.ConnectionClosed:
                return
            except TimeoutError:  # an idle client keeps no slot: it is closed, and ours reconnects when it sends
                ws.close(CloseCode.NORMAL_CLOSURE, f"idle for {self.idle_seconds:g} s")
                return
            start = time.monotonic()
            try:
                if isinstance(msg, str):
                    raise TypeError("expected a binary msgpack frame, got a text frame")
                obs = decode(msg)
                t0 = time.monotonic()
                result = self._infer(obs, fixed[0] if fixed else None)
                if not fixed:
                    fixed.append(signature(obs))
                    key = tuple(sorted(fixed[0].items()))
                    with self._open_lock:
                        self.shapes[key] = self.shapes.get(key, 0) + 1
                timing = {"infer_ms": (time.monotonic() - t0) * 1000.0}
                if prev_total_ms is not None:
                    timing["prev_total_ms"] = prev_total_ms
                result["server_timing"] = timing
                ws.send(msgpack_numpy.packb(result))
            except websockets.exceptions.ConnectionClosed:
                return
            except Exception as e:  # noqa: BLE001 - reported to the client in one line, like openpi's text frame
                # one line per refusal on the server's terminal (a client sending garbage cannot flood it with
                # tracebacks); the traceback at DEBUG, where a policy's own failure is looked into
                logger.error("refused an observation from %s: %s", _peer(ws), one_line(e))
                logger.debug("the refusal's traceback:\n%s", traceback.format_exc())
                try:
                    ws.send(one_line(e))
                    ws.close(CloseCode.INTERNAL_ERROR, "Internal server error: see the previous frame")
                except websockets.exceptions.ConnectionClosed:
                    pass
                return
            prev_total_ms = (time.monotonic() - start) * 1000.0

    def serve_forever(self) -> None:
        self._serving = True
        self._server.serve_forever()

    def start(self) -> "PolicyServer":
        """Serve from a background (daemon) thread; returns self."""
        if self._thread is None:
            self._serving = True
            self._thread = threading.Thread(target=self._server.serve_forever, name=f"policy-server:{self.port}",
                                            daemon=True)
            self._thread.start()
        return self

    def shutdown(self) -> None:
        """Stop accepting connections, close open ones, wait for their handlers. Idempotent."""
        if self._stopped:
            return
        self._stopped = True
        if self._serving:
            self._server.shutdown()
        else:
            self._server.socket.close()
        if self._thread is not None:
            self._thread.join(timeout=30)

    def __enter__(self) -> "PolicyServer":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.shutdown()


def serve(policy: JaxPolicy | HostPolicy, host: str = "127.0.0.1", port: int = 8000,
          metadata: Mapping[str, Any] | None = None, mapping: ObsMapping | str | None = None, *,
          api_key: str | None = None, block: bool = True) -> PolicyServer:
    """Serve ``policy`` over openpi's protocol. ``block=True`` serves until KeyboardInterrupt (then shuts down);
    ``block=False`` starts a background thread and returns the running :class:`PolicyServer`."""
    server = PolicyServer(policy, host, port, metadata, mapping, api_key)
    if not block:
        return server.start()
    logger.info("serving %s on %s (family %s)", server.metadata.get("policy"), server.url, server.metadata["family"])
    return serve_until_interrupted(server)


def serve_until_interrupted(server: PolicyServer) -> PolicyServer:
    """Serve in this thread until KeyboardInterrupt (Ctrl-C), then shut down and let the interrupt through (the
    command exits 130, as every command does on Ctrl-C)."""
    try:
        server.serve_forever()
    finally:
        server.shutdown()
    return server
