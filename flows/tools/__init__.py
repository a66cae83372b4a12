"""The user-facing tools over a store, called by the command line (flows/cli/) and the flows: the 3D viewer
(``viewer``), the nerfstudio/COLMAP exports and cloud scoring (``interchange``), rendering a scene along a path
(``render``), the run summary and manifest (``report``) and the per-scene dashboard (``dashboard``)."""
