"""Systems (static structure), tasks and their registry."""

from diffcontact.systems.base import System, Task
from diffcontact.systems.registry import BENCHMARK_TASKS, build_task

__all__ = ["BENCHMARK_TASKS", "System", "Task", "build_task"]
