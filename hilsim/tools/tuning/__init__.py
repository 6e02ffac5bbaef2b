"""Tuning and identification, each on the real services: step experiments with physics, sensors and the
controller as separate processes in lockstep (:mod:`.rig`, :mod:`.rig_run`, :mod:`.rig_types`), the
step-response figures of the arm paper's Table II (:mod:`.metrics`) and ``hilsim report step``
(:mod:`.step_report`), PID auto-tuning (``hilsim tune``, :mod:`.autotune`), a link's inertia from
primitive bodies (``hilsim inertia``, :mod:`.inertia`), and ``hilsim identify`` (:mod:`.identify`): a
real drive's response fitted from data, and a twin that responds the same."""
