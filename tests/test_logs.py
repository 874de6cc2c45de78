import io
import logging

import pytest

from stg_node.logs import configure_logging, parse_level


@pytest.fixture
def clean_root():
    root = logging.getLogger()
    saved_handlers, saved_level = root.handlers[:], root.level
    yield root
    root.handlers[:] = saved_handlers
    root.setLevel(saved_level)


def test_level_comes_from_environment(monkeypatch, clean_root):
    monkeypatch.setenv("STG_LOG_LEVEL", "warning")
    stream = io.StringIO()
    assert configure_logging(stream=stream) == logging.WARNING
    logging.getLogger("stg_node.x").info("hidden")
    logging.getLogger("stg_node.x").warning("shown")
    text = stream.getvalue()
    assert "shown" in text and "hidden" not in text
    assert "stg_node.x" in text and "WARNING" in text


def test_explicit_level_wins_and_reconfigure_adds_no_handler(monkeypatch, clean_root):
    monkeypatch.setenv("STG_LOG_LEVEL", "ERROR")
    stream = io.StringIO()
    configure_logging("DEBUG", stream=stream)
    configure_logging("DEBUG", stream=stream)
    logging.getLogger("t").debug("once")
    assert stream.getvalue().count("once") == 1


@pytest.mark.parametrize("text, level", [("debug", 10), ("INFO", 20), ("15", 15), (None, 20), ("", 20)])
def test_parse_level(text, level):
    assert parse_level(text) == level


def test_bad_level_is_a_clear_error():
    with pytest.raises(ValueError, match="STG_LOG_LEVEL"):
        parse_level("loud")


def test_default_handler_follows_the_current_stderr(monkeypatch, clean_root):
    """Configured once, then stderr is redirected (test capture, contextlib.redirect_stderr):
    the lines go to the stderr of the moment, never to a stream that was replaced."""
    clean_root.handlers[:] = [h for h in clean_root.handlers if not getattr(h, "_stg_node_handler", False)]
    first, second = io.StringIO(), io.StringIO()
    monkeypatch.setattr("sys.stderr", first)
    configure_logging("INFO")
    logging.getLogger("stg_node.x").info("one")
    monkeypatch.setattr("sys.stderr", second)
    first.close()
    logging.getLogger("stg_node.x").info("two")
    assert "two" in second.getvalue() and "one" not in second.getvalue()
