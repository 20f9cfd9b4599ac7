"""``python -m lifecycle_site.serve [daphne's options] lifecycle_site.asgi:application``: daphne,
answering properly at the limits of its HTTP layer (docs/api.md, "Limits").

Under daphne, Twisted's HTTPChannel drops the connection without a word when the request line
(method, path, query) is longer than 16 KiB, answers a bare "400" with no body when the header
lines are too long or too many, and reads any request body, whatever its size, into memory or a
temporary file before Django sees it. Here daphne's channel answers instead:

* 414 for a request line over LINE_LIMIT bytes,
* 431 for a header line over LINE_LIMIT, header lines over HEADERS_LIMIT in all (request line
  included), or more than Twisted's 500 header lines,
* 413 for a body over DATA_UPLOAD_MAX_MEMORY_SIZE (settings.py), before it is read (a chunked
  body once that much has come),
* 400 with a reason for what is not HTTP at all,

in the API's JSON error shape for paths under /api/, as a short HTML page otherwise. The
connection is closed after the answer; what the client still sends is read and dropped for a
few seconds, so that it sees the answer rather than a reset connection.

With ``LIFECYCLE_WEB_PROCESSES`` above 1, this starts that many daphne processes on one socket
instead (web_processes.py).
"""
from __future__ import annotations

import json
import os
import sys
from html import escape

# daphne.cli first: it installs the asyncio reactor, which must come before Twisted's HTTP code.
from daphne.cli import CommandLineInterface
from daphne.http_protocol import HTTPFactory
from twisted.web import http

from lifecycle_site.api.limits import size_text
from ros_gateway.shared import environment

LINE_LIMIT = 16 * 1024  # Twisted's own limit for one line (its LineReceiver.MAX_LENGTH)
HEADERS_LIMIT = 32 * 1024  # twice Twisted's: an id or query just under LINE_LIMIT still fits
LINGER_S = 5.0
REASONS = {400: "Bad Request", 413: "Content Too Large", 414: "URI Too Long", 431: "Request Header Fields Too Large"}
CODES = {400: "bad_request", 413: "body_too_large", 414: "uri_too_long", 431: "headers_too_large"}


class LimitedChannel(http.HTTPChannel):
    """Twisted's HTTP/1.1 channel with an answer, not a dropped connection, at each limit."""

    MAX_LENGTH = LINE_LIMIT
    totalHeadersSize = HEADERS_LIMIT
    body_limit = 1024 * 1024  # set from the settings by install()
    _refused = False
    _chunked_bytes = 0

    # --- where Twisted would drop the connection or answer a bare 400 -----------------------
    def lineLengthExceeded(self, line: bytes) -> None:
        if self._HTTPChannel__first_line:  # still on the request line
            parts = line.split(b" ", 2)
            self._refuse(414, f"The request line (method, path and query) is longer than {size_text(LINE_LIMIT)}; "
                         "send a shorter path or query.", parts[1] if len(parts) > 1 else b"")
        else:
            self._refuse(431, f"A header line of the request is longer than {size_text(LINE_LIMIT)}.")

    def lineReceived(self, line: bytes):
        if self._refused:
            return None
        if not self._HTTPChannel__first_line and self._receivedHeaderSize + len(line) > self.totalHeadersSize:
            self._refuse(431, f"The request's header lines (request line included) are longer than "
                         f"{size_text(HEADERS_LIMIT)} in all.")
            return None
        return super().lineReceived(line)

    def headerReceived(self, line: bytes) -> bool:
        if self._receivedHeaderCount >= self.maxHeaders:
            self._refuse(431, f"The request has more than {self.maxHeaders} header lines.")
            return False
        return super().headerReceived(line)

    def allHeadersReceived(self) -> None:
        if self.length is not None and self.length > self.body_limit:  # before "100 Continue"
            self._refuse(413, self._too_large(), limit=self.body_limit)
            return
        self._chunked_bytes = 0
        super().allHeadersReceived()

    def rawDataReceived(self, data: bytes) -> None:
        if self._refused:
            return
        if self.length is None and not self._handlingRequest:  # a chunked body: framing counts too
            self._chunked_bytes += len(data)
            if self._chunked_bytes > self.body_limit:
                self._refuse(413, self._too_large(), limit=self.body_limit)
                return
        super().rawDataReceived(data)

    def dataReceived(self, data: bytes) -> None:
        if self._refused:
            return  # the rest of what was refused: dropped
        super().dataReceived(data)

    def _respondToBadRequestAndDisconnect(self) -> None:
        self._refuse(400, "The request is not valid HTTP/1.1 (a malformed request line, header or body framing).")

    # --- the answer -----------------------------------------------------------------------------
    def _too_large(self) -> str:
        return (f"The request body is larger than {size_text(self.body_limit)}, the most this site takes; "
                "nothing was done.")

    def _refuse(self, status: int, message: str, target: bytes | None = None, **details: int) -> None:
        if self._refused or self.transport is None:
            return
        self._refused = True
        if target is None:
            target = getattr(self, "_path", b"") or b""
        if b"/api/" in target.split(b"?", 1)[0]:
            body = json.dumps({"error": {"code": CODES[status], "message": message, **details}}).encode()
            kind = b"application/json"
        else:
            title = f"{status} {REASONS[status]}"
            body = (f"<!doctype html><html><head><meta charset=\"utf-8\"><title>{title}</title></head>"
                    f"<body><h1>{title}</h1><p>{escape(message)}</p>"
                    f"<p>{'Go back and send less.' if status != 400 else ''}</p></body></html>").encode()
            kind = b"text/html; charset=utf-8"
        self.transport.write(
            b"HTTP/1.1 %d %s\r\nContent-Type: %s\r\nContent-Length: %d\r\nConnection: close\r\n\r\n%s"
            % (status, REASONS[status].encode(), kind, len(body), body)
        )
        # Closing outright while the client still sends would reset the connection, and the
        # client could lose the answer: close our side, drop what comes, end it after LINGER_S.
        half_close = getattr(self.transport, "loseWriteConnection", None)
        if half_close is None:
            self.transport.loseConnection()
        else:
            half_close()
            self.setTimeout(LINGER_S)


def _channel(factory: HTTPFactory) -> http._GenericHTTPChannelProtocol:
    return http._GenericHTTPChannelProtocol(LimitedChannel())


def install() -> None:
    """Make daphne's HTTP factory build LimitedChannel, with the body limit of the settings."""
    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "lifecycle_site.settings")
    from django.conf import settings

    if settings.DATA_UPLOAD_MAX_MEMORY_SIZE is not None:  # None: Django sets no limit, nor do we
        LimitedChannel.body_limit = settings.DATA_UPLOAD_MAX_MEMORY_SIZE
    else:
        LimitedChannel.body_limit = sys.maxsize
    HTTPFactory.protocol = _channel


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    try:
        processes = environment.whole("LIFECYCLE_WEB_PROCESSES", 1, minimum=1, maximum=32, unit="processes")
    except environment.SettingError as exc:
        raise SystemExit(str(exc)) from None
    if processes > 1:
        from lifecycle_site import web_processes

        raise SystemExit(web_processes.serve(processes, argv, dict(os.environ)))
    install()
    CommandLineInterface().run(argv)


if __name__ == "__main__":
    main()
