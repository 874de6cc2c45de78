"""A subscriber's receive channels, one per lane: FIFO, or keep-last with a draining thread.

Why a thread for keep-last: ZeroMQ's PUB drops the *newest* message when a queue is at its
high-water mark, and a backlog also waits in kernel socket buffers where a reader cannot
see it. Draining only when the application asks would therefore hand out stale frames. A
:class:`LatestChannel` reads its SUB socket continuously in a small thread (each message
is a pointer hand-over, zero-copy) and keeps only the newest message per topic in a
mailbox: queues stay empty, nothing is dropped at a HWM, and the application gets the
freshest frame whenever it asks. The thread alone touches the SUB socket; the application
side talks to it through an inproc PAIR (subscribe / stop commands one way, "mail
arrived" wake-ups the other), so a zmq poller can wait on it like on any socket.
"""

from __future__ import annotations

import itertools
import logging
import threading

import zmq

from stg_node.bus.sockets import EVENTS, NOBLOCK, POLLIN, recv_multipart
from stg_node.bus.topics import Lane

log = logging.getLogger(__name__)

_MAX_MAILBOX_TOPICS = 1024
_ids = itertools.count()


class DirectChannel:
    """FIFO: messages are read from the SUB socket one at a time, when asked."""

    keep_last = False

    def __init__(self, sock: zmq.Socket, lane: Lane):
        self.sock = sock
        self.lane = lane
        self.pollable = sock

    def subscribe(self, prefix: bytes) -> None:
        self.sock.subscribe(prefix)

    def take(self) -> list:
        # EVENTS (~1 us) rather than a NOBLOCK recv raising zmq.Again (~5 us) when empty;
        # POLLIN means a whole multipart message is there, so the recv cannot block.
        if not self.sock.get(EVENTS) & POLLIN:
            return []
        return [recv_multipart(self.sock)]

    def close(self) -> None:
        self.sock.close(linger=0)


class LatestChannel:
    """Keep-last: a thread drains the SUB socket into a one-message-per-topic mailbox."""

    keep_last = True

    def __init__(self, context: zmq.Context, sock: zmq.Socket, lane: Lane):
        self.lane = lane
        self._lock = threading.Lock()
        self._mailbox: dict[bytes, list] = {}
        endpoint = f"inproc://stg-latest-{id(self)}-{next(_ids)}"
        worker_end = context.socket(zmq.PAIR)
        worker_end.linger = 0
        worker_end.bind(endpoint)
        self.pollable = context.socket(zmq.PAIR)  # the application's end
        self.pollable.linger = 0
        self.pollable.connect(endpoint)
        self._thread = threading.Thread(
            target=self._run, args=(sock, worker_end), name=f"stg-sub-{lane.name}", daemon=True
        )
        self._thread.start()  # from here on only the thread touches sock and worker_end

    def subscribe(self, prefix: bytes) -> None:
        self.pollable.send(b"S" + prefix)

    def take(self) -> list:
        pollable = self.pollable
        while pollable.get(EVENTS) & POLLIN:  # consume wake-ups; the mailbox is the truth
            pollable.recv()
        with self._lock:
            if not self._mailbox:
                return []
            items = list(self._mailbox.values())
            self._mailbox.clear()
        return items

    def _run(self, sock: zmq.Socket, ctl: zmq.Socket) -> None:
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        poller.register(ctl, zmq.POLLIN)
        try:
            while True:
                events = dict(poller.poll())
                if ctl in events:
                    command = ctl.recv()
                    if command == b"stop":
                        return
                    if command[:1] == b"S":
                        sock.subscribe(command[1:])
                if sock in events:
                    newest: dict[bytes, list] = {}
                    while sock.get(EVENTS) & POLLIN:  # everything queued, without an exception at the end
                        frames = recv_multipart(sock)
                        key = frames[0].bytes
                        newest.pop(key, None)  # re-insert: order follows the newest arrivals
                        newest[key] = frames
                    with self._lock:
                        was_empty = not self._mailbox
                        for key, frames in newest.items():
                            self._mailbox.pop(key, None)
                            self._mailbox[key] = frames
                        while len(self._mailbox) > _MAX_MAILBOX_TOPICS:
                            self._mailbox.pop(next(iter(self._mailbox)))
                    if was_empty:
                        ctl.send(b"n")
        except zmq.ZMQError as exc:
            if exc.errno not in (zmq.ETERM, zmq.ENOTSOCK):  # context torn down under us: just stop
                log.exception("keep-last reader on lane %s failed", self.lane.name)
        except Exception:  # never die silently: the application would wait forever
            log.exception("keep-last reader on lane %s failed", self.lane.name)
        finally:
            sock.close(linger=0)
            ctl.close(linger=0)

    def close(self) -> None:
        try:
            self.pollable.send(b"stop", NOBLOCK)
        except zmq.ZMQError:
            pass
        self._thread.join(timeout=5.0)
        if self._thread.is_alive():
            log.error("keep-last reader on lane %s did not stop", self.lane.name)
        self.pollable.close(linger=0)
        with self._lock:
            self._mailbox.clear()
