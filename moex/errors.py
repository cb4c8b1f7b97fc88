"""The one exception type for a user's bad input; the CLI turns it into a one-line error, exit 2."""


class ConfigError(ValueError):
    """A config value, data file or run folder the user supplied is invalid.

    The message is one sentence naming the key and the allowed values.
    """


class Interrupted(Exception):
    """Work stopped on request (SIGINT/SIGTERM): training after saving its state, an evaluation
    before writing anything. Re-running the same command continues."""


def never() -> bool:
    """A `stop` that never asks to stop."""
    return False


def stop_if_asked(stop, what: str) -> None:
    """Between chunks of long work: `Interrupted` when `stop()` says a signal came."""
    if stop():
        raise Interrupted(f"{what} stopped by a signal before finishing")


def check(condition: bool, message: str) -> None:
    """Raise `ConfigError(message)` unless `condition` holds."""
    if not condition:
        raise ConfigError(message)


def check_range(key: str, value: float, low: float, high: float, *, low_open=False) -> None:
    """Check `low <= value <= high` (or `low < value` with `low_open`), naming `key` on failure."""
    ok = (value > low if low_open else value >= low) and value <= high
    bracket = "(" if low_open else "["
    check(ok, f"{key}={value} is outside {bracket}{low}, {high}]")


def check_positive(key: str, value: float) -> None:
    check(value > 0, f"{key}={value} must be positive")


def positive_or_auto(key: str, value):
    """`value` as a float where it is a positive number, or "auto" (a value the data settle
    later); a `ConfigError` naming `key` otherwise."""
    if value == "auto":
        return value
    number = isinstance(value, int | float)
    check(number and value > 0, f"{key}={float(value) if number else value} must be positive, "
                                f"or auto")
    return float(value)


def closest_first(word: str, choices) -> list[str]:
    """`choices` ordered by their likeness to `word` (the closest spelling first)."""
    import difflib

    return sorted(choices, key=lambda c: -difflib.SequenceMatcher(None, word, c).ratio())
