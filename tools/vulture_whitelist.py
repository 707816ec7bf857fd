"""Names vulture reports as unused that are used where it cannot see: read by tests/test_dead_code.py
together with the tree (never imported or run). Each entry says who uses the name."""

from vulture.whitelist_utils import Whitelist

_ = Whitelist()

# kernels/__init__.py: the module's lazy attributes (PEP 562), called by the import system
_.__getattr__
_.__dir__

# numba @intrinsic: the typing context and every argument are part of the signature numba calls
# (kernels/_krlst_simd.py, kernels/covariance.py); the code generator reads the arguments from `args`
_.typingctx
_.bits

# tests/test_linuxcnc.py: a module-scoped autouse fixture, run by pytest for every test of the file
_._linuxcnc_here

# tests/conftest.py: a pytest hook (the longest test files handed to the workers first), called by pytest
_.pytest_collection_modifyitems
