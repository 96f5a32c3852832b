"""CITATION.cff at the repository's root says what to cite, in CFF 1.2.0."""
from pathlib import Path

import pytest

CITATION = Path(__file__).resolve().parents[1] / "CITATION.cff"


def test_the_citation_file_names_the_software_and_the_methods():
    if not CITATION.is_file():
        pytest.skip("CITATION.cff is not beside the tests (installed package)")
    yaml = pytest.importorskip("yaml")
    data = yaml.safe_load(CITATION.read_text())
    assert data["cff-version"] == "1.2.0"
    assert (data["title"], data["type"], data["license"]) == ("tpscore", "software", "MIT")
    assert data["authors"] == [{"name": "tpscore developers"}]
    titles = " ".join(reference["title"] for reference in data["references"]).lower()
    for method in ("thin-plate", "compactly supported", "bi-laplacian"):
        assert method in titles
    # CFF requires a type, a title and authors of every reference
    for reference in data["references"]:
        assert reference["type"] and reference["title"] and reference["authors"]
