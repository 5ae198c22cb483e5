"""The client side of openpi's policy-server WebSocket protocol: evaluate any openpi policy (or one of ours, served
by ``openpi_server.py``) as a host policy.

Wire protocol (openpi ``serve_policy.py`` / ``openpi_client``), see docs/openpi.md:
  * ``ws://host:port`` (default port 8000), no compression, no message size limit, optional
    ``Authorization: Api-Key <key>`` header; ``GET /healthz`` answers 200 ``OK``.
  * on connect the server sends one binary frame: msgpack(metadata dict) (may be ``{}``);
  * each request is a binary msgpack(observation dict); the reply a binary msgpack(result dict) holding
    ``"actions"`` float [H, D] (plus ``"server_timing"`` / ``"policy_timing"``);
  * a *text* frame is a server-side error (openpi's: a traceback; ours: one line), after which the server closes
    the connection.
Arrays travel in openpi's msgpack-numpy encoding (:mod:`sc3_jax.policies.msgpack_numpy`); observations and actions
are translated by an :class:`~sc3_jax.policies.openpi_mappings.ObsMapping`.
"""
from __future__ import annotations

import inspect
import logging
import threading
import time
from typing import Any, Mapping

import numpy as np
import websockets
import websockets.exceptions
import websockets.sync.client

from sc3_jax.core.errors import UserError
from sc3_jax.policies import msgpack_numpy
from sc3_jax.policies.openpi_mappings import ObsMapping, fit_rows, get_mapping

__all__ = ["PolicyServerError", "PolicyConnectionError", "PolicyTimeoutError", "WebsocketClientPolicy",
           "DEFAULT_CHUNK"]

logger = logging.getLogger(__name__)

DEFAULT_CHUNK = 25  # paper: policy chunk 25


class PolicyServerError(RuntimeError):
    """The policy server reported an error (a text frame: openpi's a traceback, ours one line)."""


class PolicyConnectionError(ConnectionError):
    """Could not (re)connect to the policy server within the retry budget."""


class PolicyTimeoutError(TimeoutError):
    """The policy server did not answer in time."""


# websockets >= 17 warns unless a directly-returned connection is requested explicitly (older versions lack the flag).
_CONNECT_KW = {"legacy": True} if "legacy" in inspect.signature(websockets.sync.client.connect).parameters else {}


def _retriable(exc: BaseException) -> bool:
    if isinstance(exc, websockets.exceptions.InvalidStatus):
        return exc.response.status_code >= 500  # 503 while a server restarts; 401/403/404 will not get better
    if isinstance(exc, websockets.exceptions.InvalidURI):
        return False
    return isinstance(exc, (OSError, websockets.exceptions.WebSocketException))  # refused, reset, timeout, closed


class WebsocketClientPolicy:
    """A :class:`HostPolicy` backed by an openpi-protocol policy server (openpi's ``serve_policy.py`` or ours).

    ``infer(obs)`` maps our observation with ``mapping`` (a preset name or :class:`ObsMapping`; None = native: our
    dict as is), sends it, and maps the reply's ``"actions"`` back to float32 [chunk, D]. ``infer_raw(dict) -> dict``
    speaks the protocol without any mapping. ``last_response`` holds the last raw reply (timings etc.).
    ``action_dim`` / ``state_dim`` / ``views``: the action dimension, state dimension and number of views of the model
    (world model / robot) these actions drive; given, a mapping carrying other dimensions or reading more views is
    refused here, before connecting (one-line UserError naming both), and native replies are checked against
    ``action_dim``. Without them, ``action_dim`` / ``state_dim`` are the mapping's (None when native) and
    ``min_views`` the views it reads, so that a world model can refuse the policy before compiling anything.
    ``chunk`` (actions returned per call): the argument, else the server metadata's ``"chunk"``, else the mapping's
    (its openpi example client's: DROID 8, ALOHA 25), else 25.

    Connection failures (refused, reset, 5xx during the handshake, connection lost between requests) are retried
    ``max_retries`` times with exponential back-off ``backoff_s * 2**i`` (capped at ``max_backoff_s``), then raise
    :class:`PolicyConnectionError` naming ``host:port``. ``timeout_s`` bounds the opening handshake and each reply
    (:class:`PolicyTimeoutError`; the connection is dropped and re-opened by the next call). A text frame from the
    server raises :class:`PolicyServerError` with the server's message.
    """

    def __init__(self, host: str = "127.0.0.1", port: int | None = 8000, mapping: ObsMapping | str | None = None,
                 api_key: str | None = None, *, chunk: int | None = None, action_dim: int | None = None,
                 state_dim: int | None = None, views: int | None = None, timeout_s: float = 60.0,
                 max_retries: int = 5, backoff_s: float = 0.5, max_backoff_s: float = 10.0):
        self.uri = host if host.startswith(("ws://", "wss://")) else f"ws://{host}"
        if port is not None:
            self.uri += f":{port}"
        self.address = self.uri.split("://", 1)[1]
        self.mapping = get_mapping(mapping)
        m = self.mapping
        if m is not None:  # before connecting: a wrong preset is not a network issue
            m.check_dims(action_dim=action_dim, state_dim=state_dim, views=views)
        self.action_dim = action_dim if action_dim is not None or m is None else m.action_dim
        self.state_dim = state_dim if state_dim is not None or m is None else m.state_dim
        self.min_views = None if m is None else m.min_views
        self.api_key, self.timeout_s = api_key, timeout_s
        self.max_retries, self.backoff_s, self.max_backoff_s = max_retries, backoff_s, max_backoff_s
        self._ws: websockets.sync.client.ClientConnection | None = None
        self._metadata: dict = {}
        self._lock = threading.Lock()
        self.last_response: dict | None = None
        self._connect()
        meta_chunk = self._metadata.get("chunk") if isinstance(self._metadata, dict) else None
        meta_chunk = meta_chunk if isinstance(meta_chunk, int) else None  # openpi's servers send none
        own_chunk = None if m is None else m.chunk  # the family's example client's execution horizon
        self.chunk = int(next(c for c in (chunk, meta_chunk, own_chunk, DEFAULT_CHUNK) if c is not None))

    @property
    def metadata(self) -> dict:
        """The metadata dict the server sent on connect."""
        return self._metadata

    def get_server_metadata(self) -> dict:  # openpi_client spelling
        return self._metadata

    def _connect(self) -> None:
        self._close()
        headers = {"Authorization": f"Api-Key {self.api_key}"} if self.api_key else None
        last: BaseException | None = None
        for attempt in range(self.max_retries + 1):
            if attempt:
                delay = min(self.backoff_s * 2 ** (attempt - 1), self.max_backoff_s)
                logger.info("policy server %s unreachable (%s); retry %d/%d in %.2fs", self.address, last, attempt,
                            self.max_retries, delay)
                time.sleep(delay)
            ws = None
            try:
                ws = websockets.sync.client.connect(self.uri, compression=None, max_size=None,
                                                    additional_headers=headers, open_timeout=self.timeout_s,
                                                    **_CONNECT_KW)
                first = ws.recv(timeout=self.timeout_s)
            except (OSError, websockets.exceptions.WebSocketException) as e:  # refused, reset, timeout, HTTP error
                if ws is not None:
                    ws.close()
                if not _retriable(e):
                    raise PolicyConnectionError(f"policy server at {self.address} refused the connection: "
                                                f"{type(e).__name__}: {e}") from e
                last = e
                continue
            if isinstance(first, str):
                ws.close()
                raise PolicyServerError(f"policy server at {self.address} sent an error instead of its metadata:\n"
                                        f"{first}")
            self._ws, self._metadata = ws, msgpack_numpy.unpackb(first)
            return
        raise PolicyConnectionError(f"could not connect to the policy server at {self.address} ({self.uri}) after "
                                    f"{self.max_retries + 1} attempts; last error: {type(last).__name__}: {last}; "
                                    "is a policy server (sc3 serve-policy, or openpi's) running there?")

    def _close(self) -> None:
        if self._ws is not None:
            try:
                self._ws.close()
            except Exception:  # noqa: BLE001
                pass
            self._ws = None

    def infer_raw(self, obs: Mapping[str, Any]) -> dict:
        """Send one observation dict as is and return the server's reply dict."""
        data = msgpack_numpy.packb(obs)
        with self._lock:
            last: BaseException | None = None
            for attempt in range(self.max_retries + 1):
                if self._ws is None:
                    if attempt:
                        time.sleep(min(self.backoff_s * 2 ** (attempt - 1), self.max_backoff_s))
                    self._connect()
                try:
                    self._ws.send(data)
                    reply = self._ws.recv(timeout=self.timeout_s)
                except TimeoutError as e:
                    self._close()  # a late reply would be read as the answer to the next request
                    raise PolicyTimeoutError(f"policy server at {self.address} did not answer within "
                                             f"{self.timeout_s}s") from e
                except websockets.exceptions.ConnectionClosed as e:
                    logger.warning("connection to policy server %s lost (%s); reconnecting", self.address, e)
                    self._close()
                    last = e
                    continue
                if isinstance(reply, str):
                    self._close()  # the server closes after an error frame
                    raise PolicyServerError(f"error in the policy server at {self.address}:\n{reply}")
                self.last_response = msgpack_numpy.unpackb(reply)
                return self.last_response
            raise PolicyConnectionError(f"lost the connection to the policy server at {self.address} "
                                        f"{self.max_retries + 1} times; last error: {last}")

    def infer(self, obs: Mapping[str, Any]) -> np.ndarray:
        """Our observation -> our action chunk float32 [chunk, D]."""
        if self.mapping is None:
            reply = self.infer_raw({k: np.asarray(v) for k, v in obs.items()})
        else:
            reply = self.infer_raw(self.mapping.to_family(obs))
        if "actions" not in reply:
            raise PolicyServerError(f"reply from the policy server at {self.address} has no 'actions' "
                                    f"(keys: {sorted(map(str, reply))})")
        if self.mapping is None:
            actions = np.asarray(reply["actions"], np.float32)
            if self.action_dim is not None and (actions.ndim != 2 or actions.shape[1] != self.action_dim):
                raise UserError(f"policy server {self.address} returned actions of shape {list(actions.shape)} but "
                                f"the model has {self.action_dim}-D actions")
            return np.ascontiguousarray(fit_rows(actions, self.chunk, "hold", f"policy server {self.address}"))
        return self.mapping.actions_to_ours(reply["actions"], self.chunk)

    def reset(self) -> None:  # openpi_client API
        pass

    def close(self) -> None:
        self._close()

    def __enter__(self) -> "WebsocketClientPolicy":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
