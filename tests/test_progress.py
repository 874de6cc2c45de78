import io
import threading
import time

import pytest

from stg_node.progress import LOG_INTERVAL_S, progress, wait_with_progress


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_log_output_is_sparse_but_reports_rate_and_total():
    out = io.StringIO()
    bar = progress(range(500), desc="work", unit="item", file=out)
    assert bar.mininterval == LOG_INTERVAL_S
    assert sum(1 for _ in bar) == 500
    text = out.getvalue()
    # a fast loop on a log stream: the first and the final redraw only, in plain ASCII
    assert text.count("work:") <= 3
    assert "500/500" in text and "item/s" in text
    assert text.isascii()


def test_terminal_output_redraws_often():
    bar = progress(total=3, desc="t", file=_Terminal())
    assert bar.mininterval < 1.0
    bar.close()


def test_disabled_bar_writes_nothing():
    out = io.StringIO()
    for _ in progress(range(10), desc="quiet", file=out, enabled=False):
        pass
    assert out.getvalue() == ""


def test_wait_with_progress_runs_the_work_elsewhere_and_passes_result_and_errors():
    out = _Terminal()
    main = threading.get_ident()

    def work():
        time.sleep(1.1)
        return threading.get_ident()

    assert wait_with_progress(work, desc="compiling", file=out) != main
    assert "compiling: 00:01 elapsed" in out.getvalue()
    with pytest.raises(ZeroDivisionError):
        wait_with_progress(lambda: 1 / 0, desc="failing", file=io.StringIO())
    quiet = io.StringIO()
    assert wait_with_progress(threading.get_ident, desc="off", enabled=False, file=quiet) == main
    assert quiet.getvalue() == ""
