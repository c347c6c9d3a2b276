"""pytest configuration: make the repository root importable as `tests.*`."""

# Modules that start subprocesses or train end to end: scheduled first, so that the long ones
# do not all land at the end of an xdist run and leave one worker busy alone.
_LONG_MODULES = ("test_resume.py", "test_multiprocess.py", "test_notebook.py", "test_train.py")


def pytest_collection_modifyitems(config, items):
  del config
  rank = lambda item: 0 if item.path.name in _LONG_MODULES or item.get_closest_marker("slow") else 1
  items.sort(key=rank)  # stable: the order within each rank is kept
