"""agent.json_files: a long JSON list read entry by entry gives what parsing it whole gives, and the same errors."""

from __future__ import annotations

import json

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from agent.json_files import NotAJsonList, iter_json_list, read_json

_scalars = st.none() | st.booleans() | st.integers(-10**12, 10**12) | st.floats(allow_nan=False) | st.text(
    alphabet=st.sampled_from(list('ab ,[]{}:"\\\n\u00e9\u2603')), max_size=8)
_values = st.recursive(_scalars, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(
    st.text(alphabet="abc[]{},:\" ", max_size=4), inner, max_size=4), max_leaves=12)


@settings(max_examples=150, deadline=None)
@given(entries=st.lists(_values, max_size=12), indent=st.sampled_from([None, 0, 2]), chunk=st.integers(1, 64),
       bom=st.booleans(), encoding=st.sampled_from(["utf-8", "utf-16-le", "utf-16", "utf-32"]))
@example(entries=[12345, 6789], indent=None, chunk=3, bom=False, encoding="utf-8")  # a number cut by a chunk's end
@example(entries=[{"a": "]},["}], indent=None, chunk=2, bom=False, encoding="utf-8")
def test_entries_read_one_at_a_time_are_the_whole_files(tmp_path_factory, entries, indent, chunk, bom, encoding):
    """Any JSON values, any chunk size, a BOM, the encodings json.load finds (UTF-16 from Windows tools)."""
    path = tmp_path_factory.mktemp("j") / "list.json"
    bom = bom and encoding == "utf-8"
    path.write_bytes(("\ufeff" if bom else "").encode() + json.dumps(entries, indent=indent).encode(encoding))
    assert list(iter_json_list(path, "candidates", chunk_chars=chunk)) == entries == read_json(path, "candidates")


@pytest.mark.parametrize("text", ['[{"a": 1}, {"a": 2}', '[{"a": 1} {"a": 2}]', '[{"a": 1},]', '[1] 2',
                                  '[{"a": tru}]', ""])
def test_broken_files_say_what_parsing_them_whole_says(tmp_path, text):
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(ValueError) as whole:
        read_json(path, "candidates")
    with pytest.raises(ValueError) as streamed:
        list(iter_json_list(path, "candidates", chunk_chars=4))
    assert str(streamed.value) == str(whole.value) and "is not valid JSON" in str(streamed.value)


def test_a_missing_file_or_another_value_is_named(tmp_path):
    with pytest.raises(ValueError, match=r"candidates file .*nope\.json does not exist"):
        list(iter_json_list(tmp_path / "nope.json", "candidates"))
    other = tmp_path / "dict.json"
    other.write_text('  {"image_id": 1}')
    with pytest.raises(NotAJsonList, match="expected a JSON list, got dict"):
        list(iter_json_list(other, "candidates"))
    empty = tmp_path / "empty.json"
    empty.write_text(" [ ] \n")
    assert list(iter_json_list(empty, "candidates")) == []
