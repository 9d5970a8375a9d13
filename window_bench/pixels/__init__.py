"""The pixel observation track (paper Section 3.2, Appendix, Table 8).

* :mod:`window_bench.pixels.encoder` - the frozen ResNet-10 backbone and the trainable
  per-view spatial aggregation fused with the 18 proprioceptive values;
* :mod:`window_bench.pixels.weights` - safetensors weights (timm ``resnet10t`` names), the
  shipped in-domain default, refusal of wrong files and of a silent random encoder;
* :mod:`window_bench.pixels.features` - ``PixelFeatures``: the backbone once per step in the
  env worker, so replay holds cached feature maps;
* :mod:`window_bench.pixels.agent` - ``PixelQCFQL``: QC-FQL on cached features;
* :mod:`window_bench.pixels.pretrain` and :mod:`window_bench.pixels.cli` - ``bench encoder``.
"""
