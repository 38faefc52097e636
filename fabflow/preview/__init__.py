"""The browser scene (viser), live and exported as one HTML file.

Modules, from data to browser:

* :mod:`~fabflow.preview.model`: :func:`build_model` precomputes everything the
  scene draws (build sequence, stations, arm poses by inverse kinematics, colours)
  as numpy arrays; no viser.
* :mod:`~fabflow.preview.inputs`: :func:`model_for_project` from a project, and the
  readers of ``fabflow simulate`` output (deviations, base poses).
* :mod:`~fabflow.preview.scene`: :class:`PreviewScene` draws a model on a viser
  server (blocks as one batched mesh) and applies steps and colour modes.
* :mod:`~fabflow.preview.gui`: the control panel; :mod:`~fabflow.preview.app`:
  :func:`serve` (live); :mod:`~fabflow.preview.export`: :func:`export_html`.
* :mod:`~fabflow.preview.command`: ``fabflow preview``; :mod:`~fabflow.build.preview`:
  the ``preview`` stage of ``fabflow build``.
"""
