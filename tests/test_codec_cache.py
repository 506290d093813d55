"""pyzeros' codec compiler (cydr) compiles once per machine, before the tests, into a
temporary directory: never into the checkout, never under one test's timeout."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from conftest import CODEC_CACHE_ENV, codec_cache_dir

REPO = Path(__file__).resolve().parents[1]


def test_codecs_compile_into_a_temporary_directory_not_the_checkout() -> None:
    import cydr._runtime as runtime

    cache = Path(os.environ[CODEC_CACHE_ENV])
    assert cache == codec_cache_dir() and cache.is_dir()
    assert Path(runtime.CYDR_CACHE_DIR) == cache
    assert not cache.resolve().is_relative_to(REPO.resolve())
    assert cache.resolve().is_relative_to(Path(tempfile.gettempdir()).resolve())


def test_the_attachment_codec_is_ready_before_any_test_serializes() -> None:
    from pyzeros.builtin_msgs import Attachment

    # Compiled at collection (conftest.pytest_collection_finish): this is a cache hit.
    assert Attachment.deserialize(Attachment(sequence_number=7).serialize()).sequence_number == 7
