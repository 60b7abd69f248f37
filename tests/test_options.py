"""BuildOptions: one set of build options with one set of defaults, seen the same by
the Python API, the command line and the HTTP form."""

import argparse

import numpy as np
import pytest

import lodserver
from lodserver.api.models import MeshCreate
from lodserver.build import build
from lodserver.cli import _flag, _parser
from lodserver.mesh import MeshError
from lodserver.options import BuildOptions

from .meshes import mesh

FIELDS = list(BuildOptions.model_fields)


def _subparser(name: str) -> argparse.ArgumentParser:
    sub = next(a for a in _parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


def _cli_defaults(command: str) -> dict:
    """What argparse fills in for each build option when no flag is given."""
    parser = _subparser(command)
    required = {"build": ["m.obj", "-o", "m.pm"], "export": ["m.obj", "-o", "m.glb"],
                "simplify": ["m.obj", "--ratio", "0.5", "-o", "m.obj"]}[command]
    args = parser.parse_args(required)
    return {name: getattr(args, name) for name in args.option_names}


def test_defaults_are_the_same_on_every_face():
    python = BuildOptions().model_dump()
    schema = MeshCreate.model_json_schema()["properties"]
    form = {name: schema[name]["default"] for name in FIELDS}
    assert _cli_defaults("build") == python
    assert form == python
    # export builds mesh files with every option; simplify with all but its own --method
    assert _cli_defaults("export") == python
    assert _cli_defaults("simplify") == {k: v for k, v in python.items() if k != "method"}
    # and a form with nothing but the file builds with exactly those (stored as
    # every record keeps them: a late option at its default left out)
    assert MeshCreate.model_validate({}).build_options() == BuildOptions().recorded()
    assert BuildOptions.check(BuildOptions().recorded()) == BuildOptions()


def test_every_option_has_a_flag_a_form_field_and_one_line_of_help():
    schema = MeshCreate.model_json_schema()["properties"]
    flags = {action.dest: action for action in _subparser("build")._actions}
    for name in FIELDS:
        assert name in schema, name
        assert name in flags and _flag(name)[0] in flags[name].option_strings, name
        description = BuildOptions.model_fields[name].description
        assert description and "\n" not in description and "``" not in description
        assert schema[name]["description"] == description
        assert description in flags[name].help.replace("%%", "%")
    # the form is the options plus the upload's name, nothing else
    assert set(schema) == set(FIELDS) | {"name"}


@pytest.mark.parametrize("values, words", [
    ({"boundary_weight": -1}, "boundary_weight must be greater than or equal to 0, got -1"),
    ({"boundary_weight": "nan"}, "boundary_weight must be a finite number"),
    ({"min_vertices": "many"}, "min_vertices must be an integer, got 'many'"),
    ({"pair_threshold": "x%"}, "pair_threshold must be a non-negative number or a percentage"),
    ({"pair_threshold": -0.5}, "pair_threshold must be a non-negative number"),
    ({"method": "voxels"}, "method must be 'qem' or 'cluster', got 'voxels'"),
    ({"uv_weight": 0}, "uv_weight must be a positive number, got 0"),
    ({"flip_cos": 2}, "flip_cos must be less than or equal to 1, got 2"),
    ({"attributes": "perhaps"}, "attributes must be true or false, got 'perhaps'"),
])
def test_bad_values_are_one_sentence_naming_the_option(values, words):
    with pytest.raises(MeshError) as caught:
        BuildOptions.check(**values)
    message = str(caught.value)
    assert words in message
    assert "\n" not in message and "pydantic" not in message and "http" not in message


def test_the_cli_names_the_flag_and_the_form_the_field(tmp_path, capsys):
    from lodserver.cli import main

    from .meshes import DATA

    code = main(["build", str(DATA / "spot.obj"), "-o", str(tmp_path / "x.pm"),
                 "--boundary-weight", "-2"])
    err = capsys.readouterr().err.strip()
    assert code == 1 and err == ("lodserver build: --boundary-weight must be greater than or "
                                 "equal to 0, got -2.0")
    assert not (tmp_path / "x.pm").exists()
    with pytest.raises(Exception) as caught:
        MeshCreate.model_validate({"colour": "red"})
    assert "colour" in str(caught.value)


def test_pair_threshold_takes_numbers_and_percentages():
    assert BuildOptions(pair_threshold=0.25).pair_threshold == "0.25"
    assert BuildOptions.model_validate({"pair_threshold": " 2% "}).pair_threshold == "2%"
    assert BuildOptions.model_validate({"pair_threshold": "1e-3"}).pair_threshold == "1e-3"
    for bad in ("inf", "-1", "1%%", "", "nan"):
        with pytest.raises(MeshError):
            BuildOptions.check(pair_threshold=bad)


def test_keywords_options_and_the_older_attribute_weights_build_the_same():
    """build(mesh, boundary_weight=2) as before, a BuildOptions, or a stored dict."""
    spot = mesh("spot")
    by_keyword = build(spot, boundary_weight=2, uv_weight=0.1)
    by_model = build(spot, BuildOptions(boundary_weight=2, uv_weight=0.1))
    by_dict = build(spot, {"boundary_weight": 2}, attribute_weights={"TEXCOORD_0": 0.1})
    for other in (by_model, by_dict):
        np.testing.assert_array_equal(other.at(500).positions, by_keyword.at(500).positions)
    assert by_keyword.metadata["options"]["boundary_weight"] == 2
    assert by_keyword.metadata["options"]["attribute_weights"]["TEXCOORD_0"] == 0.1
    # the options differ from the defaults' build
    default = build(spot)
    assert not np.array_equal(default.at(500).positions, by_keyword.at(500).positions)
    with pytest.raises(TypeError, match="not a build option"):
        build(spot, boundary_wieght=2)


def test_lock_border_is_an_option_of_build():
    positions = np.array([[x, y, 0.05 * x * y] for y in range(5) for x in range(6)], float)
    index = np.arange(30).reshape(5, 6)
    faces = []
    for i in range(4):
        for j in range(5):
            a, b, c, d = index[i, j], index[i, j + 1], index[i + 1, j + 1], index[i + 1, j]
            faces += [(a, b, c), (a, c, d)]
    sheet = lodserver.Mesh(positions, np.array(faces))
    pm = build(sheet, lock_border=True)
    base = pm.at(pm.base_vertices)
    border = {(x, y) for x in range(6) for y in range(5) if x in (0, 5) or y in (0, 4)}
    assert border <= {(p[0], p[1]) for p in base.positions}
    assert pm.metadata["options"]["lock_border"] is True
    assert pm.metadata["options"]["locked_vertices"] == len(border)


def test_version_is_the_package_version():
    from importlib.metadata import version

    assert lodserver.__version__ == version("lodserver")
    assert lodserver.BuildOptions is BuildOptions


def test_decimate_options_are_the_build_options_in_the_kernels_units():
    m = mesh("spot")
    options = BuildOptions(pair_threshold="1%", boundary_weight=2, seam_weight=0.5,
                           flip_cos=0.3, min_vertices=10, preserve_volume=False)
    kernel = options.decimate_options(m)
    # a percentage becomes mesh units; the rest is copied as it is
    assert kernel.pair_threshold == pytest.approx(0.01 * m.bounding_box_diagonal)
    assert (kernel.boundary_weight, kernel.seam_weight, kernel.flip_cos) == (2, 0.5, 0.3)
    assert kernel.min_vertices == 10 and kernel.preserve_volume is False
    assert kernel.attribute_weights == options.attribute_weights()
    # what only a direct caller of decimate chooses keeps its default
    assert kernel.max_collapses is None and kernel.parts is None
    with pytest.raises(MeshError, match="distance"):
        BuildOptions(pair_threshold="1e400").decimate_options(m)
