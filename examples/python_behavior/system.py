"""The behavior system hosting CIRCLE_AROUND: a Python process that serves what a C++ behavior
system serves (the generic and typed services, health, reflection, /metrics) and registers with
the coordinator. Started like a C++ system, with the data channel it flies through:

    build/venv/bin/python examples/python_behavior/system.py --robot-id drone1 \\
        --listen 127.0.0.1:0 --port-file circle.ports --coordinator 127.0.0.1:50060 \\
        --channel 127.0.0.1:50051 --clock sim

or by the local launcher: deploy/local/launch.py --python-systems examples/python_behavior/system.py
"""

from behaviorlib.system import run_system

from circle_around import CircleAround


def behaviors(context):
    """The behaviors of this system, made once the process knows its robot and channel."""
    if context.channel is None:
        raise SystemExit("python_circle_around flies through the data channel: give --channel")
    return [CircleAround(context.channel)]


if __name__ == "__main__":
    raise SystemExit(run_system(behaviors, system="python_circle_around"))
