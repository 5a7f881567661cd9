"""Generated native code for the control loops: casadi functions compiled to C and called
through ctypes.

- :mod:`controllers.native.codegen`: compile a casadi function to a shared library, cache it
  on disk and load it.
- :mod:`controllers.native.compiled_inverse`: the NLS inverse (range ends, warm start,
  safeguarded Newton) in one C call.
- :mod:`controllers.native.nmpc_horizon`: the NMPC's horizon prediction and its sensitivities.
- :mod:`controllers.native.nmpc_step`: the NMPC's real-time iteration (linearization, QP
  matrices, unconstrained optimum) and memory step, one C call each.
"""
