"""The release's record codecs, numpy only: what every domain's release files are made of.

- :mod:`.example`: ``tf.train.Example`` <-> numpy, without protobuf or TensorFlow;
- :mod:`.png`: the release's PNG frames (Pillow or libspng, behind the ``release`` extra).

They sit below the domains (``rlu.domains``), whose release families decode and encode records
with them, and below ``rlu.data.release``, which frames, downloads and converts the files.
"""
