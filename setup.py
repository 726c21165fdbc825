"""Build configuration that pyproject.toml cannot express: the shipped scenes and releases.

The scene files live in the top-level ``scenes/`` folder of the source checkout; wheels carry
them as ``vvtbench/scenes`` (see ``vvtbench.scene.scene.SCENES_DIR``), with the shipped
tetrahedralizations in ``scenes/meshes``. Everything else is in
pyproject.toml.
"""

from setuptools import find_packages, setup

setup(
    packages=find_packages(include=["vvtbench*", "solvers*"])
    + ["vvtbench.scenes", "vvtbench.scenes.suites", "vvtbench.scenes.families",
       "vvtbench.releases"],
    package_dir={"vvtbench.scenes": "scenes", "vvtbench.releases": "releases"},
    package_data={"vvtbench.scenes": ["*.toml", "meshes/*.npz"],
                  "vvtbench.scenes.suites": ["*.toml"],
                  "vvtbench.scenes.families": ["*.toml"], "solvers": ["weights/*.npz"],
                  "vvtbench.releases": ["*.toml", "*.sha256", "*.lock"]},
)
