"""SoftSMPL (thesis ch. 3): soft-tissue dynamics of parametric bodies, learned from registered meshes.

- :mod:`.data`: the in-memory training format (:class:`SoftTissueSequence`, :class:`SoftTissueData`)
  and a synthetic test signal (:func:`synthetic_softtissue_data`).
- :mod:`.dyna`: the reader of Dyna's registered meshes (needs ``h5py`` and the user's SMPL file).
- :mod:`.models`: the soft-tissue autoencoder, the pose autoencoder, the GRU regressor, the losses.
- :mod:`.train`: ``train_softtissue`` (``simgen train softtissue``) and ``load_softtissue_model``.

Submodules import torch; this package imports nothing heavy.
"""
