"""backends/progress.py: casadi's printed output caught per thread (captured_output)."""

import sys
import threading

from daemodel.backends.progress import captured_output


def test_captures_in_threads_at_once_keep_each_threads_text_and_set_the_streams_back(capsys):
    """Two threads' captures overlapping (a in, b in, a out, b out), the main thread printing meanwhile: each text
    holds its own thread's output alone, the main thread's reaches the streams, and both streams are set back.
    (Each capture saving and restoring the streams it found left sys.stdout and sys.stderr b's StringIO after
    concurrent solves: every later print lost.)"""
    before = sys.stdout, sys.stderr
    a_in, b_in, printed, a_out = (threading.Event() for _ in range(4))
    texts = {}

    def a():
        with captured_output() as text:
            a_in.set()
            b_in.wait()
            printed.wait()
            print("from a")
        texts["a"] = text.getvalue()
        a_out.set()

    def b():
        a_in.wait()
        with captured_output() as text:
            b_in.set()
            a_out.wait()
            print("from b", file=sys.stderr)
        texts["b"] = text.getvalue()

    threads = [threading.Thread(target=a), threading.Thread(target=b)]
    for thread in threads:
        thread.start()
    b_in.wait()
    print("from main")
    print("main's error", file=sys.stderr)
    printed.set()
    for thread in threads:
        thread.join()
    assert (sys.stdout, sys.stderr) == before
    assert texts == {"a": "from a\n", "b": "from b\n"}
    out, err = capsys.readouterr()
    assert (out, err) == ("from main\n", "main's error\n")


def test_a_capture_inside_a_capture_gives_the_outer_its_text_back():
    with captured_output() as outer:
        print("one")
        with captured_output() as inner:
            print("two")
        print("three")
    assert (outer.getvalue(), inner.getvalue()) == ("one\nthree\n", "two\n")
