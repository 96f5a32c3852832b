"""The showcase: what makes faces and pictures to show the methods, and no method uses.

- :mod:`.datasets`: procedural faces for the tests, and the builders of the shipped
  average-face database and physical-skin template;
- :mod:`.demo_faces`: the demo's real faces, scanned in the Bosphorus formats;
- :mod:`.render`: headless pictures of faces (z-buffer renders, heat maps, GIFs);
- :mod:`.viewer`: the browser page of a result or a rig.

The showcase imports the face vocabulary, the kernels and the physical skin; nothing
in :mod:`tpscore.face` or the method packages imports it. Its data files are in
``tpscore/data/``.
"""
