"""The numeric core: pure JAX, fixed shapes, float32 on the step's path. The paper's Fig. 1 stage by
stage, each file named by its stage letter so that the tree reads in data-flow order:
``a_segment`` (segmentation), ``b_features`` (ORS and characteristic vector), ``c_filters`` (binary
filters, shape envelopes), ``d_classify`` (GP classifier, open set), ``e_pose`` (pose regression),
``f_maptransform`` (map transformation), ``g_track`` (EKF tracker); ``frontend`` runs a–c,
``pipeline.step`` all of them. Beside them: ``model`` (the parameter tree ``Model``), ``scan`` (the
padded scan), ``geometry`` (angles and the ORS, S and O frames, also for the host), ``buckets`` (how
the step is compiled). Nothing here imports the host side (io, drivers, train, cli, sensors, errors,
viz, the viewer, the simulator): it uses the GP library (``gtsjax.gp``) and ``gtsjax.precision``, which
sits below both (``tests/test_layers.py`` holds this)."""
