"""The arm paper's engineering tools: inertia from primitives (:mod:`.inertia`), step-response
figures (:mod:`.metrics`), step experiments on the real services in lockstep (:mod:`.rig`), the
Table II report (:mod:`.step_report`) and PID auto-tuning (:mod:`.tuning`)."""
