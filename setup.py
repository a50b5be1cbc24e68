"""Package list for setuptools (the rest of the metadata is in pyproject.toml).

The Alembic environment stays at the repository root in migrations/ (where developers and
alembic.ini expect it) and is installed as the package `service.migrations`, so that
`tiltlab db upgrade` finds it in a regular, non-editable install; the dashboard's web/ is
installed as `service.web` the same way (service/resources.py finds both).
"""

from setuptools import find_packages, setup

setup(
    packages=[
        *find_packages(include=["service", "service.*"]),
        "service.migrations",
        "service.migrations.versions",
        "service.web",
    ],
    package_dir={"service.migrations": "migrations", "service.web": "web"},
)
