"""data: the synthetic scene generator (``synthetic``) and tensor loaders for scene pixels (``dataset``).

Scene *structure* (cameras, split, normalisation) is loaded by ``uncertsplat.sfm.scene.load_scene``.
"""
