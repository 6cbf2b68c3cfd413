"""mkf_ros.ros.signals: the teardown after a signal waits for rclpy's own signal thread."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import pytest
import rclpy
from rclpy.context import Context

from mkf_ros.ros.signals import await_signal_shutdown, ends_on_signal

pytestmark = pytest.mark.ros


def test_waits_until_another_thread_shuts_the_context_down() -> None:
    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=rclpy.SignalHandlerOptions.NO)
    try:
        done_at: list[float] = []

        def shut_down_later() -> None:
            time.sleep(0.2)
            done_at.append(time.monotonic())
            ctx.shutdown()

        t = threading.Thread(target=shut_down_later)
        t.start()
        assert await_signal_shutdown(ctx, timeout=10.0)
        assert done_at, "returned before the context was shut down"
        assert not ctx.ok()
        t.join()
    finally:
        ctx.try_shutdown()


def test_gives_up_on_a_context_nobody_shuts_down() -> None:
    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=rclpy.SignalHandlerOptions.NO)
    try:
        assert await_signal_shutdown(ctx, timeout=0.05) is False
        assert ctx.ok()
    finally:
        ctx.try_shutdown()
    assert await_signal_shutdown(ctx, timeout=0.0)  # shut down: no wait


def test_a_signal_ends_the_block_quietly_and_anything_else_propagates() -> None:
    """What the console scripts take for a signal: KeyboardInterrupt, or any exception once
    the context is shut down (rclpy's RCLError "context is not valid" from an executor whose
    wait started after the shutdown); an error while the context is fine is not one."""
    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=rclpy.SignalHandlerOptions.NO)
    try:
        with pytest.raises(ValueError, match="a real error"), ends_on_signal(ctx):
            raise ValueError("a real error")
        threading.Timer(0.05, ctx.shutdown).start()  # rclpy's signal thread, a little later
        with ends_on_signal(ctx):
            raise KeyboardInterrupt
        assert not ctx.ok()  # it waited for the shutdown before ending the block
        with ends_on_signal(ctx):
            raise RuntimeError("failed to initialize wait set: the given context is not valid")
    finally:
        ctx.try_shutdown()


def test_sigint_with_a_second_executor_thread_exits_cleanly_every_time(tmp_path) -> None:
    """The estimator's shape (a main executor and a service thread with its own executor),
    SIGINT while both wait: the process exits 0, never by a signal, in 20 starts. Fifty more
    executors widen the window in which rclpy's signal thread is still triggering their guard
    conditions: without the wait this script segfaults within the first few starts."""
    script = tmp_path / "two_executors.py"
    script.write_text(textwrap.dedent("""
        import sys, threading
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from mkf_ros.ros.signals import ends_on_signal
        rclpy.init()
        node, helper = rclpy.create_node("a"), rclpy.create_node("b")
        main_ex, helper_ex = SingleThreadedExecutor(), SingleThreadedExecutor()
        main_ex.add_node(node)
        helper_ex.add_node(helper)
        # more signal guard conditions for rclpy's signal thread to trigger: a wider window
        others = [SingleThreadedExecutor() for _ in range(50)]
        def spin_helper():
            while rclpy.ok():
                try:
                    helper_ex.spin_once(timeout_sec=2.0)
                except Exception:
                    return
        t = threading.Thread(target=spin_helper, daemon=True)
        t.start()
        node.create_timer(0.001, lambda: None)  # the main thread wakes often, as under load
        print("ready", flush=True)
        with ends_on_signal(rclpy.get_default_context()):
            main_ex.spin()
        main_ex.shutdown()
        for ex in others:
            ex.shutdown()
        helper_ex.wake()
        t.join(5.0)
        helper_ex.shutdown()
        node.destroy_node()
        helper.destroy_node()
        rclpy.try_shutdown()
        sys.exit(0)
    """))
    env = dict(os.environ)
    codes = []
    for _ in range(20):
        p = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, env=env)
        assert p.stdout is not None and p.stdout.readline().strip() == "ready"
        time.sleep(0.05)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=30)
        codes.append(p.returncode)
        assert p.returncode == 0, f"exit {p.returncode}:\n{err}"
    assert codes == [0] * 20
