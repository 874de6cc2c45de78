import io

from stg_node.progress import LOG_INTERVAL_S, progress


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
