"""How the scenario's processes run: a fleet's arrays (``fleet:``) and what ``hilsim up`` does when a service
dies (``restart:``)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, ValidationInfo, field_validator

from hilsim.core.config.base import _Model, known_services


class FleetConfig(_Model):
    """How a fleet (``robots`` > 1) is computed (:mod:`hilsim.core.fleet`)."""

    arrays: bool = Field(True, description="robots > 1: a process serving every robot's sensors or controller "
                         "(sensors@*, controller@*) steps them as numpy arrays and trades one fleet-wide sample per "
                         "step with physics (fleet/truth/joint_states, fleet/joint_states, fleet/joint_commands); "
                         "the per-robot keys are still published for whoever subscribes; robots with encoder or "
                         "control rates of their own run robot by robot (hilsim.core.scenario.array_misfit)")


RestartPolicy = Literal["no", "on-failure"]


class RestartConfig(_Model):
    """What ``hilsim up`` does when a service dies (like compose's ``restart:``): ``no`` (report
    and stop the run) or ``on-failure`` (start it again, at most ``max_attempts`` times per
    service, after ``backoff`` seconds, doubled at each attempt). Physics is never restarted: it
    holds sim time and the robot's true state, which a new process would not have."""

    services: dict[str, RestartPolicy] = Field(
        default_factory=dict, description="per service name, or 'default' for the others: no | on-failure"
    )
    max_attempts: int = Field(3, ge=1, le=100, description="restarts per service and run")
    backoff: float = Field(0.5, ge=0, le=60, description="wall seconds before the first restart (doubled each time)")

    @field_validator("services", mode="before")
    @classmethod
    def _no_is_not_false(cls, v: Any) -> Any:
        # YAML reads a bare `no` as False (compose has the same trap): take it as the policy "no"
        if isinstance(v, dict):
            return {k: "no" if p is False else p for k, p in v.items()}
        return v

    @field_validator("services")
    @classmethod
    def _known(cls, v: dict[str, str], info: ValidationInfo) -> dict[str, str]:
        known = known_services(info)
        for name, policy in v.items():
            if known is not None and name != "default" and name not in known:
                raise ValueError(f"unknown service {name!r}; expected 'default' or one of {', '.join(known)}")
            if name == "physics" and policy != "no":
                raise ValueError("physics cannot be restarted: sim time and the robot's true state would be lost")
        return v

    def policy(self, service: str) -> str:
        """The policy of ``service`` (its own entry, else ``default``, else no); physics: no. A
        composed process ``a+b`` (:mod:`hilsim.launch.compose`) is restarted only if each of its members is."""
        if "+" in service:
            return "on-failure" if all(self.policy(s) == "on-failure" for s in service.split("+")) else "no"
        service = service.split("@")[0]  # robots > 1: controller@arm3, controller@* (hilsim.core.fleet)
        if service == "physics":
            return "no"
        return self.services.get(service, self.services.get("default", "no"))
