"""A single-threaded executor that keeps its wait set while the entities stay the same.

rclpy's executor rebuilds its wait set in Python over every entity of every node at each wake
(callback-group checks, a context manager per handle, a new rcl wait set, a pointer lookup per
entity after the wait), and wakes once more after each callback to put the entity back. On this
project's control path that was about a third of the CPU of the composed simulation and the
larger part of a node's sample -> command latency. rclcpp's StaticSingleThreadedExecutor solves the
same problem the same way: the entity collection is built once, rebuilt only when an entity or node
is added or removed (`wake`, which every create_* and destroy_* of a node calls), and the rcl wait
set is refilled from that collection at each wait.

Callbacks run in the order rclpy's SingleThreadedExecutor runs them (waitables, then per node
timers, subscriptions, guard conditions, clients and services), one at a time in the calling
thread, so code written for it runs unchanged; test/test_executor.py checks this against rclpy's
executor. rclpy's EventsExecutor would be cheaper still, but in rclpy 7.1.6 its services never
answered and it ignored SIGTERM (docs/architecture.md, "The executor").
"""

import inspect
import threading
import time
from contextlib import ExitStack

from rclpy.exceptions import InvalidHandle
from rclpy.executors import (
    ConditionReachedException,
    ExternalShutdownException,
    ShutdownException,
    SingleThreadedExecutor,
    TimeoutException,
)
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.subscription import Subscription
from rclpy.task import Task
from rclpy.timer import Timer
from rclpy.utilities import timeout_sec_to_nsec
from rclpy.waitable import NumberOfEntities


class StaticSingleThreadedExecutor(SingleThreadedExecutor):
    """rclpy's SingleThreadedExecutor with a wait set kept between wakes (module docstring)."""

    def __init__(self, *, context=None):
        super().__init__(context=context)
        self._plan = None  # the kept _WaitPlan
        self._plan_stale = True  # build a new plan at the next wait
        self._waiting = False  # a thread is in the wait: the plan's handles must stay held
        # reentrant: rclpy's SIGINT handling wakes the executor from the waiting thread itself
        self._plan_lock = threading.RLock()

    # ---- what makes the kept wait set stale ---------------------------------------------------
    def wake(self):
        """An entity was created or destroyed (every Node.create_*/destroy_* calls this)."""
        self._discard_plan()
        super().wake()

    def add_node(self, node):
        added = super().add_node(node)
        self._discard_plan()
        return added

    def remove_node(self, node):
        super().remove_node(node)
        self._discard_plan()

    def shutdown(self, timeout_sec=None):
        done = super().shutdown(timeout_sec)
        self._discard_plan()
        return done

    def _discard_plan(self):
        """Build a new plan at the next wait, and release the kept handles now unless a thread
        waits on them (then it releases them when its wait ends). A handle destroyed while kept
        is destroyed when released, as under rclpy's executor after its wait."""
        with self._plan_lock:
            self._plan_stale = True
            if not self._waiting and self._plan is not None:
                self._plan, plan = None, self._plan
                plan.close()

    # ---- the wait ------------------------------------------------------------------------------
    def _wait_for_ready_callbacks(self, timeout_sec=None, nodes=None, condition=lambda: False):
        """As rclpy's, on the kept wait set (rclpy's own for a subset of the nodes)."""
        if nodes is not None:
            yield from super()._wait_for_ready_callbacks(timeout_sec, nodes, condition)
            return
        timeout_nsec = timeout_sec_to_nsec(getattr(timeout_sec, 'timeout', timeout_sec))
        deadline = time.monotonic_ns() + timeout_nsec if timeout_nsec > 0 else None
        yielded_work = False
        while not yielded_work and not self._is_shutdown and not condition():
            # tasks in progress first: a coroutine resumed, a future's done callback
            busy = False
            if self._tasks:
                with self._tasks_lock:
                    self._tasks = [t for t in self._tasks if not t[0].done()]
                    tasks = list(self._tasks)
                for task, entity, node in reversed(tasks):
                    if not task.executing() and not task.done():
                        yielded_work = True
                        yield task, entity, node
                busy = any(not t[0].done() for t in tasks)

            if deadline is not None:
                timeout_nsec = max(0, deadline - time.monotonic_ns())
            for entity, node, take in self._wait(timeout_nsec, busy):
                yielded_work = True
                yield self._make_handler(entity, node, take), entity, node

            if timeout_nsec == 0:
                raise TimeoutException()
        if self._is_shutdown:
            raise ShutdownException()
        if condition():
            raise ConditionReachedException()

    def _wait(self, timeout_nsec, busy):
        """Wait on the kept wait set; the entities to run, in rclpy's order, as (entity, node,
        take). `busy`: a task is in progress, so callback groups may refuse entities: this wait
        gets a set of its own built with rclpy's checks."""
        try:
            with self._plan_lock:
                if self._plan_stale or busy or self._plan.filtered:
                    if self._plan is not None:
                        self._plan.close()
                    self._plan = _WaitPlan(self, filtered=busy)
                    self._plan_stale = False
                plan = self._plan
                wait_set = plan.refill()
                self._waiting = True
            wait_set.wait(timeout_nsec)
            if self._is_shutdown:
                raise ShutdownException()
            if not self._context.ok():
                raise ExternalShutdownException()
            return plan.ready()
        finally:
            with self._plan_lock:
                self._waiting = False
                if self._plan_stale:
                    self._discard_plan()

    def _make_handler(self, entity, node, take_from_wait_list):
        """rclpy's handler without its guard triggers: they only made the executor rebuild its wait
        set to put the entity back, and the kept wait set never left it out. A subscription or
        timer whose callback is a plain function is run at once (_DirectCall)."""
        entity._executor_event = True
        if take_from_wait_list in _DIRECT_KINDS.values():
            return _DirectCall(self, entity, take_from_wait_list)

        async def handler():
            if self._is_shutdown or not entity.callback_group.beginning_execution(entity):
                entity._executor_event = False
                return
            with self._work_tracker:
                call_coroutine = take_from_wait_list(entity)
                entity._executor_event = False
                try:
                    if call_coroutine is not None:
                        await call_coroutine()
                finally:
                    entity.callback_group.ending_execution(entity)

        task = Task(handler, executor=self)
        with self._tasks_lock:
            self._tasks.append((task, entity, node))
        return task


class _DirectCall:
    """What _make_handler returns for a subscription or timer whose callback is a plain function:
    the Task interface the executor's callers use (call it, then exception() and result()), with
    the work done in the call itself. rclpy wraps every callback in a Task and a coroutine
    (20-30 us of CPU a wake here, docs/architecture.md "The executor"); only a coroutine callback
    needs them."""

    __slots__ = ('_executor', '_entity', '_run', '_exception')

    def __init__(self, executor, entity, run):
        self._executor, self._entity, self._run = executor, entity, run
        self._exception = None

    def __call__(self):
        executor, entity = self._executor, self._entity
        if executor._is_shutdown or not entity.callback_group.beginning_execution(entity):
            entity._executor_event = False
            return
        try:
            with executor._work_tracker:
                self._run(entity)
        except Exception as exc:  # noqa: BLE001 - raised by spin_once, as a Task's would be
            self._exception = exc
        finally:
            entity._executor_event = False
            entity.callback_group.ending_execution(entity)

    def exception(self):
        return self._exception

    def result(self):
        if self._exception is not None:
            raise self._exception

    def done(self):
        return True

    def cancelled(self):
        return False


def _run_subscription(sub):
    """Take one message and call the callback with it (rclpy's _take_subscription and
    _execute, as a plain call)."""
    try:
        with sub.handle:
            taken = sub.handle.take_message(sub.msg_type, sub.raw)
    except InvalidHandle:  # destroyed since the wait
        return
    sub._executor_event = False
    if taken is None:
        return
    if sub._callback_type is Subscription.CallbackType.MessageOnly:
        sub.callback(taken[0])
    else:
        sub.callback(*taken)


def _run_timer(timer):
    """Mark the timer called and call its callback (rclpy's _take_timer and _execute)."""
    try:
        with timer.handle:
            timer.handle.call_timer()
    except InvalidHandle:
        return
    timer._executor_event = False
    timer.callback()


# the kinds of entity whose plain callbacks run as a _DirectCall, and how
_DIRECT_KINDS = {'subscription': _run_subscription, 'timer': _run_timer}


class _WaitPlan:
    """The entities of an executor's nodes, their handles held (so that none is destroyed while
    in the wait set), the rcl wait set they fill, and their order."""

    def __init__(self, executor, filtered):
        self.filtered = filtered
        with ExitStack() as stack:  # released if the plan fails half-built
            self._build(executor, executor.can_execute if filtered else _may_run, stack)
            self._stack = stack.pop_all()

    def _build(self, executor, keep, stack):
        self._rank = {}  # (kind, handle pointer) -> (rank, entity, node, take)
        handles = {kind: [] for kind in _KINDS}
        self.node_guards, self.waitables = [], []
        counts = NumberOfEntities(num_gcs=2)  # the executor's guard and SIGINT's
        for node in executor.get_nodes():
            for kind, (entities, take, count) in _KINDS.items():
                for entity in filter(keep, getattr(node, entities)):
                    try:
                        stack.enter_context(entity.handle)
                    except InvalidHandle:
                        continue
                    handles[kind].append(entity.handle)
                    setattr(counts, count, getattr(counts, count) + 1)
                    run = getattr(executor, take)
                    if kind in _DIRECT_KINDS and not inspect.iscoroutinefunction(entity.callback):
                        run = _DIRECT_KINDS[kind]
                    rank = (len(self._rank), entity, node, run)
                    self._rank[kind, entity.handle.pointer] = rank
                    if kind == 'guard_condition':
                        self.node_guards.append(entity)
            for waitable in filter(keep, node.waitables):
                try:
                    stack.enter_context(waitable)
                except InvalidHandle:
                    continue
                self.waitables.append((waitable, node, executor._take_waitable))
                counts += waitable.get_num_entities()
        for gc in (executor._guard, executor._sigint_gc):
            stack.enter_context(gc.handle)
            handles['guard_condition'].append(gc.handle)
        stack.enter_context(executor.context.handle)
        self.wait_set = _rclpy.WaitSet(
            counts.num_subscriptions,
            counts.num_guard_conditions,
            counts.num_timers,
            counts.num_clients,
            counts.num_services,
            counts.num_events,
            executor.context.handle,
        )
        adders = {kind: getattr(self.wait_set, f'add_{kind}') for kind in _KINDS}
        self._fill = [(adders[kind], handles[kind]) for kind in _KINDS]

    def refill(self):
        """The wait set with every entity in it again (a wait leaves only the ready ones)."""
        wait_set = self.wait_set
        wait_set.clear_entities()
        for add, handles in self._fill:
            for handle in handles:
                add(handle)
        for gc in self.node_guards:  # a guard triggered but not yet handled stays triggered
            if gc._executor_triggered:
                gc.trigger()
        for waitable, _, _ in self.waitables:
            waitable.add_to_wait_set(wait_set)
        return wait_set

    def ready(self):
        """After a wait, the entities to run as (entity, node, take), as rclpy orders them:
        waitables, then per node timers, subscriptions, guard conditions, clients, services."""
        wait_set = self.wait_set
        run = [w for w in self.waitables if w[0].is_ready(wait_set) and _may_run(w[0])]
        found = []
        for kind in _KINDS:
            for pointer in wait_set.get_ready_entities(kind):
                ranked = self._rank.get((kind, pointer))
                if ranked is not None:
                    found.append(ranked)
        for gc in self.node_guards:
            if not gc._executor_triggered and any(r[1] is gc for r in found):
                gc._executor_triggered = True
        for gc in self.node_guards:  # triggered before and not handled yet
            if gc._executor_triggered and not any(r[1] is gc for r in found):
                found.append(self._rank['guard_condition', gc.handle.pointer])
        found.sort(key=lambda ranked: ranked[0])
        for _, entity, node, take in found:
            if isinstance(entity, Timer) and not entity.handle.is_timer_ready():
                continue  # a cancelled timer (rclpy works around the same rcl issue)
            if _may_run(entity):
                run.append((entity, node, take))
        return run

    def close(self):
        self._stack.close()


# per kind of entity (rcl's name, as the wait set's add_* and get_ready_entities spell it): the
# Node property listing them, the executor's method that takes one's work, the count's name;
# in the order rclpy's executor runs the ready entities of a node
_KINDS = {
    'timer': ('timers', '_take_timer', 'num_timers'),
    'subscription': ('subscriptions', '_take_subscription', 'num_subscriptions'),
    'guard_condition': ('guards', '_take_guard_condition', 'num_guard_conditions'),
    'client': ('clients', '_take_client', 'num_clients'),
    'service': ('services', '_take_service', 'num_services'),
}


def _may_run(entity):
    """Whether the entity's callback group lets it run (krang_ros.spin.Polled never does)."""
    return entity.callback_group.can_execute(entity)
