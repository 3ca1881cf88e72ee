"""The terminal writers for diagnostics and live status (onfly.console): stderr, never stdout;
redrawn in place on a terminal, one line per call elsewhere."""

import io

from onfly.console import live_line, status


class Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_status_goes_to_stderr_alone(capsys):
    status("2 episode(s) ended with a method error")
    status()
    out, err = capsys.readouterr()
    assert out == "" and err == "2 episode(s) ended with a method error\n\n"


def test_a_live_line_is_redrawn_on_a_terminal_and_one_line_per_call_elsewhere():
    tty = Tty()
    live_line("t   1.0 s  goal  12.0 m", width=30, stream=tty)
    live_line("t   6.0 s  goal   9.5 m  searching the hallway, a long subtask", width=30, stream=tty)
    live_line("done", width=30, final=True, stream=tty)
    frames = tty.getvalue().split("\r")[1:]
    assert [len(f.rstrip("\n")) for f in frames] == [30, 30, 30]  # cut and padded to the width
    assert frames[1].startswith("t   6.0 s  goal   9.5 m  searc") and "\n" not in "".join(frames[:2])
    assert frames[2] == "done".ljust(30) + "\n"  # only the final one ends its line
    log = io.StringIO()
    live_line("t   1.0 s", width=5, stream=log)
    live_line("t   6.0 s", width=5, final=True, stream=log)
    assert log.getvalue() == "t   1.0 s\nt   6.0 s\n"  # whole lines, not cut
