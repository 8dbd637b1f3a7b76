"""The semantic map (issue 14): per-pixel class labels of keyframes (`segmentation`: an ONNX
model, or labels the camera sent) fused into 3-D objects with Bayesian class histograms
(`objects`), off the tracking thread (`worker`), stored in the map database
(`storage.objects`). `classes` holds the default class table (ADE20K-32)."""
