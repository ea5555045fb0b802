"""Typed errors of the runtime."""


class QueryError(ValueError):
    """A query was malformed; the message says what is wrong and is sent back as the error reply."""


class QueryFailed(RuntimeError):
    """A query got an error reply, or no reply at all."""
