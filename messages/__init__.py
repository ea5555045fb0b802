"""relaxmap's bus messages (msgspec structs) and key expressions. Imports nothing from services or sim."""

from messages.types import *  # noqa: F403
from messages.types import ALL_MESSAGES, ALL_REPLIES, Message  # noqa: F401
