"""Export: bodies for other tools. ``gltf``: rigged binary glTF 2.0 (skin, skeleton, morph targets);
``morphs``: the semantic directions of a model as morph targets."""
