"""The original RL Unplugged release without TensorFlow.

- :mod:`.framing`: TFRecord reader / writer (masked CRC-32C, whole-file gzip, streaming);
- :mod:`.families`: the registry of the release's families (each domain declares its own, with
  its decoding into loader-shaped arrays and into Segments; ``tf.train.Example`` and PNG codecs in
  :mod:`rlu.codecs`);
- :mod:`.catalog`: bucket paths and shard counts for every registered task;
- :mod:`.download`: resumable, checksum-recorded HTTPS download into a cache dir;
- :mod:`.convert`: shards -> native store; :mod:`.jobs`: one job per shard on the one runner (local
  processes or a Ray cluster), one assembly per dataset; :mod:`.load`:
  ``load_dataset(..., source="release")``.

Reading needs the ``release`` extra (google-crc32c, Pillow); importing this package does not.
"""
