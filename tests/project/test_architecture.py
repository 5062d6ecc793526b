"""The package's import graph: no module imports one that (directly or not) imports it back.
The layer order itself is the import-linter contract in pyproject.toml (`make lint`)."""

import grimp


def test_no_import_cycles_between_modules():
    graph = grimp.build_graph("recon")
    cycles = []
    for module in sorted(graph.modules):
        for imported in sorted(graph.find_modules_directly_imported_by(module)):
            back = graph.find_shortest_chain(importer=imported, imported=module)
            if back is not None:
                cycles.append(" -> ".join((module, *back)))
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_a_method_module_that_fails_to_import_is_an_error(monkeypatch):
    """The registry imports every method; a broken one raises instead of vanishing."""
    import pytest

    from recon.models import registry

    monkeypatch.setitem(registry.METHOD_MODULES, "broken", "recon.models.does_not_exist")
    with pytest.raises(ModuleNotFoundError):
        registry.import_methods()
