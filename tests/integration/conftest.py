"""The fixtures of the packages whose commands the tests here drive across package lines: the tiny datasets of
tests/dataset, the drawn dataset and trained run of tests/perception, the published dataset of tests/publish."""

from tests.dataset.conftest import tiny_config, tiny_dataset  # noqa: F401
from tests.perception.conftest import (  # noqa: F401
    _one_thread,
    _rendered,
    drawn_dataset,
    rendered_depth,
    rendered_frame,
    trained_run,
)
from tests.publish.conftest import source_dataset  # noqa: F401
