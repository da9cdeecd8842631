"""End-to-end tests: whole stacks under a real supervisord. Every one is marked ``slow``
(``pytest -m "not slow"`` runs the unit and integration layers only)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest

from tests.e2e.users import UserEnv, UserUnavailable, ordinary_user

HERE = Path(__file__).parent


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if HERE in Path(item.fspath).parents:
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="session")
def ordinary_user_or_why() -> Iterator[UserEnv | str]:
    """A :class:`UserEnv` for ``nobody`` (built once per session), or why there is none."""
    with ExitStack() as stack:
        try:
            env: UserEnv | str = stack.enter_context(ordinary_user())
        except UserUnavailable as exc:
            env = str(exc)
        yield env


@pytest.fixture
def user_env(ordinary_user_or_why: UserEnv | str) -> UserEnv:
    """``nobody``'s environment; the test is skipped where there is none."""
    if isinstance(ordinary_user_or_why, str):
        pytest.skip(ordinary_user_or_why)
    return ordinary_user_or_why
