"""Reading a Channels test communicator (channels.testing.WebsocketCommunicator) in unit tests."""
from __future__ import annotations


async def receive_until(communicator, text: str, timeout: float = 5) -> str:
    """The first message that contains ``text`` (those before it are skipped); each message
    must come within ``timeout`` seconds."""
    while True:
        message = await communicator.receive_from(timeout=timeout)
        if text in message:
            return message
