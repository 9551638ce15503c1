"""JSON inputs nested deeper than any nrpose file are refused before Python's recursive decoder."""
import pytest

from nrpose.errors import FileFormatError
from nrpose.io import load_character
from nrpose.io.jsonfile import MAX_DEPTH, document_depth, nesting_depth, read_json


def test_nesting_depth_ignores_brackets_in_strings():
    assert nesting_depth('{"a": [1, {"b": "[[[["}], "c": "\\"[["}') == 3
    assert nesting_depth("3") == 0


def test_document_depth_equals_the_text_scan_on_random_documents():
    """The depth counted on decoded values (what parse_json checks) is the text scan's, with
    empty containers, strings holding brackets and escaped quotes."""
    import json
    import random
    rng = random.Random(7)

    def value(d):
        r = rng.random()
        if d > 12 or r < 0.3:
            return rng.choice([1, 2.5, "x[{", '"]}', None, True, "\\", [], {}])
        if r < 0.65:
            return [value(d + 1) for _ in range(rng.randrange(4))]
        return {f"k{i}[": value(d + 1) for i in range(rng.randrange(4))}

    for _ in range(300):
        doc = value(0)
        assert document_depth(doc) == nesting_depth(json.dumps(doc))
    assert document_depth(3) == 0 and document_depth([]) == 1 and document_depth({"a": [[], {}]}) == 3


@pytest.mark.parametrize("depth", [MAX_DEPTH + 1, 100_000])
def test_deep_json_refused_with_its_depth(tmp_path, depth):
    path = tmp_path / "deep.json"
    path.write_text("[" * depth + "]" * depth)
    with pytest.raises(FileFormatError, match=f"{depth} deep"):
        read_json(path, "pose file")
    ok = tmp_path / "ok.json"
    ok.write_text("[" * MAX_DEPTH + "]" * MAX_DEPTH)
    assert isinstance(read_json(ok, "pose file"), list)


def test_deep_gltf_refused(tmp_path):
    path = tmp_path / "deep.gltf"
    path.write_text('{"asset": ' + "[" * 5000 + "]" * 5000 + "}")
    with pytest.raises(FileFormatError, match="5001 deep"):
        load_character(path)


def test_numbers_json_does_not_have_are_refused_or_named():
    """Python's json reads NaN, Infinity and 1e999 (as infinity); JSON has no such numbers."""
    from nrpose.io.jsonfile import check_finite, parse_json
    for text in ('{"a": 1e999}', '{"a": [NaN]}', '{"a": -Infinity}'):
        with pytest.raises(FileFormatError, match="not valid JSON"):
            parse_json(text, "x.json", "a test file")
    doc = parse_json('{"a": [1, {"b": -1e999}]}', "x.json", "a test file", finite=False)
    with pytest.raises(FileFormatError, match=r"x\.json: a\[1\]\.b = -inf: JSON has no such number"):
        check_finite(doc, "x.json")
    check_finite(parse_json('{"a": [1.5, {"b": 1e308}]}', "x.json", "a test file"), "x.json")


def test_depth_counted_across_blocks_and_json_size_bounded(monkeypatch):
    """Nesting is counted block by block (bounded memory) and carries over block edges; a JSON
    text past MAX_JSON_CHARS is refused before it is scanned or decoded."""
    import nrpose.io.jsonfile as jsonfile
    pad = " " * (1 << 22)                      # 4 MB: the next brackets start a new block
    assert nesting_depth("[" + pad + "[[" + "]]]") == 3
    assert nesting_depth("[[" + pad + "]]" + "[") == 2
    monkeypatch.setattr(jsonfile, "MAX_JSON_CHARS", 100)
    with pytest.raises(FileFormatError, match="is 0 MB of JSON"):
        jsonfile.parse_json("[" + "0," * 60 + "0]", "x.json", "a test file")


def test_a_json_file_too_large_is_refused_before_it_is_read(tmp_path, monkeypatch):
    import nrpose.io.jsonfile as jsonfile
    path = tmp_path / "pose.json"
    path.write_text('{"a": [1, 2, 3]}')
    assert read_json(path, "pose file") == {"a": [1, 2, 3]}
    monkeypatch.setattr(jsonfile, "MAX_JSON_BYTES", path.stat().st_size - 1)
    monkeypatch.setattr(jsonfile, "read_input_text", lambda *a, **k: pytest.fail("the file was read"))
    with pytest.raises(FileFormatError, match=r"pose\.json: pose file is 0 MB \(at most 0 MB of JSON\)"):
        read_json(path, "pose file")
