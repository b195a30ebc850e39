"""One headless Chromium for the whole test session, driven from each test's own event loop.

Playwright's objects belong to the event loop that started its driver, and starting the driver
and the browser costs seconds a test on a loaded machine. So both live on a loop of their own,
in a thread, for the session; each test reaches them through `Remote` proxies, which run every
call on that loop, and gets fresh contexts (pages) that are closed after it.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import inspect
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

from hil_sim.links.wire_loop import WireLoop

T = TypeVar("T")
CALL_TIMEOUT_S = 120.0  # a sync call (a property, `locator`): never a wait on the page


def _is_playwright(value: Any) -> bool:
    return type(value).__module__.startswith("playwright.")


class BrowserThread:
    """The playwright driver and one Chromium on an event loop in a thread of their own."""

    def __init__(self, executable: str, args: list[str]) -> None:
        self._wire = WireLoop("browser")
        self.loop = self._wire.loop
        self._wire.start()
        self._executable, self._args = executable, args
        self._pw: Any = None
        self._browser: Any = None
        self.run(self._launch())

    async def _launch(self) -> None:
        from playwright.async_api import async_playwright

        if self._pw is None:
            self._pw = await async_playwright().start()
        self._browser = await self._pw.chromium.launch(
            executable_path=self._executable, args=self._args
        )

    def run(self, coro: Coroutine[Any, Any, T]) -> T:
        """Run a coroutine on the browser's loop and wait for it (outside any event loop)."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result()

    def call(self, fn: Callable[[], T]) -> T:
        """Run a plain call on the browser's loop and wait for it."""
        future: concurrent.futures.Future[T] = concurrent.futures.Future()

        def call() -> None:
            try:
                future.set_result(fn())
            except BaseException as exc:  # handed to the caller
                future.set_exception(exc)

        self.loop.call_soon_threadsafe(call)
        return future.result(CALL_TIMEOUT_S)

    async def wait(self, awaitable: Any) -> Any:
        """Await, from a test's loop, something of the browser's loop."""

        async def inner() -> Any:
            return await awaitable

        return await self._wire.run(inner())

    def browser(self) -> Remote:
        """The browser, relaunched first if it went away (a crash in an earlier test)."""
        if not self.call(self._browser.is_connected):
            self.run(self._launch())
        return Remote(self._browser, self)

    async def close_contexts(self) -> None:
        """Close every context (and so page) a test opened."""

        async def close_all() -> None:
            for context in list(self._browser.contexts):
                await context.close()

        await self.wait(close_all())

    def stop(self) -> None:
        """Close the browser and the driver, end the loop and the thread."""

        async def stop() -> None:
            await self._browser.close()
            await self._pw.stop()

        try:
            self.run(stop())
        finally:
            self._wire.stop()


class Remote:
    """A playwright object of the browser's loop, used as if it were on the test's loop."""

    def __init__(self, obj: Any, owner: BrowserThread) -> None:
        object.__setattr__(self, "_obj", obj)
        object.__setattr__(self, "_owner", owner)

    def _wrap(self, value: Any) -> Any:
        if _is_playwright(value):
            return Remote(value, self._owner)
        if isinstance(value, list) and any(_is_playwright(v) for v in value):
            return [self._wrap(v) for v in value]
        if inspect.isawaitable(value):  # e.g. an event's `value`: a future of the browser's loop
            return self._later(value)
        return value

    async def _later(self, awaitable: Any) -> Any:
        return self._wrap(await self._owner.wait(awaitable))

    def __getattr__(self, name: str) -> Any:
        value = self._owner.call(lambda: getattr(self._obj, name))
        if not callable(value) or _is_playwright(value):
            return self._wrap(value)
        if inspect.iscoroutinefunction(value):

            async def call_async(*args: Any, **kwargs: Any) -> Any:
                coro = value(*_unwrap(args), **_unwrap(kwargs))
                return self._wrap(await self._owner.wait(coro))

            return call_async

        def call(*args: Any, **kwargs: Any) -> Any:
            return self._wrap(self._owner.call(lambda: value(*_unwrap(args), **_unwrap(kwargs))))

        return call

    async def __aenter__(self) -> Any:
        return self._wrap(await self._owner.wait(self._obj.__aenter__()))

    async def __aexit__(self, *exc: Any) -> Any:
        return await self._owner.wait(self._obj.__aexit__(*exc))

    def __repr__(self) -> str:
        return f"Remote({self._obj!r})"


def _unwrap(value: Any) -> Any:
    if isinstance(value, Remote):
        return object.__getattribute__(value, "_obj")
    if isinstance(value, tuple):
        return tuple(_unwrap(v) for v in value)
    if isinstance(value, dict):
        return {k: _unwrap(v) for k, v in value.items()}
    return value
