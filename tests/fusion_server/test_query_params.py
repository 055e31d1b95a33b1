"""Empty optional query parameters are dropped before FastAPI reads them (fusion_server.query_params)."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from fusion_server.query_params import drop_empty

OPTIONAL = frozenset({"bbox", "min_score", "cls name"})


@pytest.mark.parametrize(("query", "kept"), [
    (b"cls=person&bbox=&min_score=", b"cls=person"),
    (b"bbox&min_score=0.3", b"bbox&min_score=0.3"),  # a bare name is kept: a client may mean it as a true flag
    (b"cls=&bbox=", b"cls="),  # cls is not optional here: left for the endpoint to refuse
    (b"cls+name=&x=1", b"x=1"),  # names compare percent-decoded, as Starlette reads them
    (b"cls%20name=&bbox=1%2C2%2C3%2C4", b"bbox=1%2C2%2C3%2C4"),  # kept pairs keep their bytes
    (b"bbox=&bbox=1,2,3,4", b"bbox=1,2,3,4"),
    (b"", b""),
])
def test_drop_empty_removes_only_empty_optional_pairs(query, kept):
    assert drop_empty(query, OPTIONAL) == kept


@given(st.lists(st.tuples(st.sampled_from(["bbox", "min_score", "cls", "limit"]),
                          st.text("ab1,.%=", max_size=4)), max_size=6))
def test_drop_empty_keeps_every_non_empty_or_required_pair_in_order(pairs):
    query = "&".join(f"{name}={value}" for name, value in pairs).encode()
    expected = "&".join(f"{name}={value}" for name, value in pairs if value or name not in OPTIONAL).encode()
    assert drop_empty(query, OPTIONAL) == expected
