"""Push-T policies: each kind's config, network, normalization and checkpoint; imports pusht, never training.

`policies.card` (the card schema) is torch-free, so ONNX serving imports it without torch; the rest needs torch:
`policies.factory.build_policy` makes a fresh policy, `policies.checkpoint` saves and loads one (safetensors and a
JSON card, no pickle), `policies.base.ActingPolicy` is what ONNX exports and acting's torch backend runs.
"""
