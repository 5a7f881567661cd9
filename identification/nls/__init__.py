"""Neural static-nonlinearity block (NLS) of the Hammerstein model: voltage u (V) -> hidden z.

The NLS maps the drive voltage ``u`` (V) to the hidden signal ``z`` (equivalent volts, i.e. the
voltage a linear, hysteresis-free actuator would need for the same deflection) that feeds the
linear ARX block. The paper (section 3.4, step e) fits it as a multilayer perceptron with three
hidden tanh layers. A static map ``u -> z`` cannot draw a hysteresis loop, so the network takes
*memory features* of the input:

Three feature sets are defined in :mod:`identification.features`: ``"play"``
(Prandtl-Ishlinskii play operators), ``"past-inputs"`` (the paper's nlarx regressors) and
``"bouc-wen"`` (normalized Bouc-Wen operators).

The package is split by job: :mod:`~identification.nls.network` (the numpy network and the
:class:`NLS` class), :mod:`~identification.nls.training` (:func:`fit_nls`, with its settings in
:mod:`~identification.nls.training_settings`, its data in :mod:`~identification.nls.training_data`
and its torch optimisation in :mod:`~identification.nls.optimisation`, the only part that imports
torch, lazily), :mod:`~identification.nls.torch_module` (the network as a torch module, for
training and export), :mod:`~identification.nls.inverse` (voltage for a target z),
:mod:`~identification.nls.export` (numpy, casadi and torch evaluators) and
:mod:`~identification.nls.files` (plain dict and arrays for the model files). Importing this
package, loading a model and evaluating it do not import torch.
"""

from identification.nls.files import NLS_FORMAT, NLS_FORMAT_VERSION
from identification.nls.inverse import NLSInverse, NLSInverseWarning
from identification.nls.network import NLS, NumpyMLP
from identification.nls.training import fit_nls
from identification.nls.training_settings import TrainingSettings

__all__ = [
    "NLS",
    "NLS_FORMAT",
    "NLS_FORMAT_VERSION",
    "NLSInverse",
    "NLSInverseWarning",
    "NumpyMLP",
    "TrainingSettings",
    "fit_nls",
]
