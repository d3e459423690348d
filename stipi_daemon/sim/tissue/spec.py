"""The ``tissue.model`` mapping of a scene file: a model's name and its parameters.

This module owns :class:`TissueModelSpec`, the pydantic form of ``tissue.model`` in a
scene (``name`` plus the model's parameters as further keys, units in their names). It
validates them through the registry, so an error names the model and the parameter with
its domain; it computes nothing.

```yaml
tissue:
  grade: "III"          # E and the loading time constant
  model:
    name: zener
    tau_sigma_s: 8.0
    tau_epsilon_s: 1.6
```
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, model_validator

from stipi_daemon.sim.tissue import build_tissue_model
from stipi_daemon.sim.tissue.base import RecoveryModel

__all__ = ["TissueModelSpec"]


class TissueModelSpec(BaseModel):
    """A scene's tissue model: ``name`` (registry) and its parameters as extra keys."""

    model_config = ConfigDict(extra="allow", frozen=True)

    name: str

    @model_validator(mode="after")
    def _valid(self) -> TissueModelSpec:
        self.build()  # ConfigError (a ValueError): pydantic reports it at tissue.model
        return self

    @property
    def parameters(self) -> dict[str, object]:
        """The parameters as given (every key but ``name``)."""
        return dict(self.model_extra or {})

    def build(self) -> RecoveryModel:
        """The validated model."""
        return build_tissue_model(self.name, self.parameters)
