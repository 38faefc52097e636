"""The build: every stage of ``fabflow build`` run in order into one output folder.

:func:`fabflow.build.runner.run_build` runs the stages, one module each
(:mod:`~fabflow.build.project`, :mod:`~fabflow.build.design`,
:mod:`~fabflow.build.plan`, :mod:`~fabflow.build.localize`,
:mod:`~fabflow.build.program`, :mod:`~fabflow.build.preview`), which share a typed
:class:`~fabflow.build.context.BuildContext`. Only the command line imports this
package; the library behind each stage lives in the room that owns it.
"""
