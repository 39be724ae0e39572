import sys, statistics, torch, warp as wp
sys.path.insert(0, '.')
wp.config.quiet = True
wp.init()
from bench.gn_block import timeit
dev = torch.device('cuda:0'); wd = wp.device_from_torch(dev); stream = wp.stream_from_torch(torch.cuda.current_stream(dev))
A = lambda x: wp.from_torch(x, return_ctype=True)
n = 73728 * 672
x = torch.randn(n, device=dev); y = torch.empty(n, device=dev, dtype=torch.float16)
opts = {"enable_backward": False}
def mk(V, strided):
    NV = n // V
    @wp.kernel(module="unique", module_options=opts)
    def k(a: wp.array(dtype=wp.float32), b: wp.array(dtype=wp.float16)):
        i = wp.tid()
        xs = wp.vector(length=V, dtype=wp.float16)
        for q in range(V):
            if wp.static(strided):
                xs[q] = wp.float16(a[i + q * NV])
            else:
                xs[q] = wp.float16(a[i * V + q])
        for q in range(V):
            if wp.static(strided):
                b[i + q * NV] = xs[q]
            else:
                b[i * V + q] = xs[q]
    return k, NV
res = {}
for V in (4,):
    for strided in (True, False):
        k, NV = mk(V, strided)
        res[f"copy V={V} {'strided' if strided else 'contig'}"] = timeit(lambda: wp.launch(k, dim=NV, inputs=[A(x), A(y)], device=wd, stream=stream), dev, 20, 3) * 1e3
# fp32 -> fp32 same
y32 = torch.empty(n, device=dev)
@wp.kernel(module="unique", module_options=opts)
def k32(a: wp.array(dtype=wp.float32), b: wp.array(dtype=wp.float32)):
    i = wp.tid()
    b[i] = a[i]
res["copy fp32->fp32 V=1"] = timeit(lambda: wp.launch(k32, dim=n, inputs=[A(x), A(y32)], device=wd, stream=stream), dev, 20, 3) * 1e3
res["torch copy fp32->fp32"] = timeit(lambda: y32.copy_(x), dev, 20, 3) * 1e3
res["torch copy fp32->fp16"] = timeit(lambda: y.copy_(x), dev, 20, 3) * 1e3
# warp-per-row concat prototype: GN2 edge shape
E, N, B, KO = 73728, 32768, 4096, 672
e = torch.randn(E, 192, device=dev); v = torch.randn(N, 159, device=dev); u = torch.randn(B, 160, device=dev)
s = torch.randint(0, N, (E,), device=dev, dtype=torch.int32).sort().values
r = torch.randint(0, N, (E,), device=dev, dtype=torch.int32).sort().values
g = torch.arange(E, device=dev, dtype=torch.int32) // 18
out = torch.empty(E, KO, device=dev, dtype=torch.float16)
W0, W1, W2, W3 = 192, 159, 159, 160
Q0, Q1, Q2, Q3 = [(w + 31) // 32 for w in (W0, W1, W2, W3)]
O1, O2, O3 = W0, W0 + W1, W0 + W1 + W2
QT = (KO - (O3 + W3) + 31) // 32
QA = Q0 + Q1 + Q2 + Q3
@wp.kernel(module="unique", module_options=opts)
def rowcat(p0: wp.array2d(dtype=wp.float32), p1: wp.array2d(dtype=wp.float32), p3: wp.array2d(dtype=wp.float32),
           i1: wp.array(dtype=wp.int32), i2: wp.array(dtype=wp.int32), i3: wp.array(dtype=wp.int32),
           o: wp.array2d(dtype=wp.float16)):
    t = wp.tid()
    row = t // 32
    lane = t - row * 32
    a1 = i1[row]
    a2 = i2[row]
    a3 = i3[row]
    xs = wp.vector(length=QA, dtype=wp.float16)
    for q in range(Q0):
        c = lane + 32 * q
        if c < W0:
            xs[q] = wp.float16(p0[row, c])
    for q in range(Q1):
        c = lane + 32 * q
        if c < W1:
            xs[Q0 + q] = wp.float16(p1[a1, c])
    for q in range(Q2):
        c = lane + 32 * q
        if c < W2:
            xs[Q0 + Q1 + q] = wp.float16(p1[a2, c])
    for q in range(Q3):
        c = lane + 32 * q
        if c < W3:
            xs[Q0 + Q1 + Q2 + q] = wp.float16(p3[a3, c])
    for q in range(Q0):
        c = lane + 32 * q
        if c < W0:
            o[row, c] = xs[q]
    for q in range(Q1):
        c = lane + 32 * q
        if c < W1:
            o[row, O1 + c] = xs[Q0 + q]
    for q in range(Q2):
        c = lane + 32 * q
        if c < W2:
            o[row, O2 + c] = xs[Q0 + Q1 + q]
    for q in range(Q3):
        c = lane + 32 * q
        if c < W3:
            o[row, O3 + c] = xs[Q0 + Q1 + Q2 + q]
    for q in range(QT):
        c = O3 + W3 + lane + 32 * q
        if c < KO:
            o[row, c] = wp.float16(0.0)
res["row-per-warp concat GN2 edges"] = timeit(lambda: wp.launch(rowcat, dim=E * 32, inputs=[A(e), A(v), A(u), A(s), A(r), A(g), A(out)], device=wd, stream=stream), dev, 20, 3) * 1e3
ref = torch.cat([e, v[s.long()], v[r.long()], u[g.long()], torch.zeros(E, KO - 670, device=dev)], 1).half()
print("rowcat correct:", torch.equal(out, ref))
V4 = 4
KV = KO // V4
E0, E1, E2, E3 = W0, W0 + W1, W0 + W1 + W2, W0 + W1 + W2 + W3
@wp.kernel(module="unique", module_options=opts)
def flatcat(p0: wp.array(dtype=wp.float32), p1: wp.array(dtype=wp.float32), p3: wp.array(dtype=wp.float32),
            i1: wp.array(dtype=wp.int32), i2: wp.array(dtype=wp.int32), i3: wp.array(dtype=wp.int32),
            o: wp.array(dtype=wp.float16)):
    t = wp.tid()
    row = t // KV
    c0 = t - row * KV
    b0 = row * W0
    b1 = i1[row] * W1
    b2 = i2[row] * W2
    b3 = i3[row] * W3
    xs = wp.vector(length=V4, dtype=wp.float16)
    for k in range(V4):
        c = c0 + k * KV
        if c < E0:
            xs[k] = wp.float16(p0[b0 + c])
        elif c < E1:
            xs[k] = wp.float16(p1[b1 + c - E0])
        elif c < E2:
            xs[k] = wp.float16(p1[b2 + c - E1])
        elif c < E3:
            xs[k] = wp.float16(p3[b3 + c - E2])
    ob = row * KO + c0
    for k in range(V4):
        o[ob + k * KV] = xs[k]
out3 = torch.empty_like(out)
res["flat V=4 concat"] = timeit(lambda: wp.launch(flatcat, dim=E * KV, inputs=[A(e.view(-1)), A(v.view(-1)), A(u.view(-1)), A(s), A(r), A(g), A(out3.view(-1))], device=wd, stream=stream), dev, 20, 3) * 1e3
print("flat correct:", torch.equal(out3, ref))
V8 = 8
KV8 = KO // V8
@wp.kernel(module="unique", module_options=opts)
def flatcat8(p0: wp.array(dtype=wp.float32), p1: wp.array(dtype=wp.float32), p3: wp.array(dtype=wp.float32),
            i1: wp.array(dtype=wp.int32), i2: wp.array(dtype=wp.int32), i3: wp.array(dtype=wp.int32),
            o: wp.array(dtype=wp.float16)):
    t = wp.tid()
    row = t // KV8
    c0 = t - row * KV8
    b0 = row * W0
    b1 = i1[row] * W1
    b2 = i2[row] * W2
    b3 = i3[row] * W3
    xs = wp.vector(length=V8, dtype=wp.float16)
    for k in range(V8):
        c = c0 + k * KV8
        if c < E0:
            xs[k] = wp.float16(p0[b0 + c])
        elif c < E1:
            xs[k] = wp.float16(p1[b1 + c - E0])
        elif c < E2:
            xs[k] = wp.float16(p1[b2 + c - E1])
        elif c < E3:
            xs[k] = wp.float16(p3[b3 + c - E2])
    ob = row * KO + c0
    for k in range(V8):
        o[ob + k * KV8] = xs[k]
out4 = torch.empty_like(out)
res["flat V=8 concat"] = timeit(lambda: wp.launch(flatcat8, dim=E * KV8, inputs=[A(e.view(-1)), A(v.view(-1)), A(u.view(-1)), A(s), A(r), A(g), A(out4.view(-1))], device=wd, stream=stream), dev, 20, 3) * 1e3
print("flat8 correct:", torch.equal(out4, ref))
from gnwarp.kernels import gn_block as K
kern = K.concat_kernel((192, 159, 159, 160), (False, True, True, True), (wp.float32,) * 4, wp.float16, KO)
out2 = torch.empty_like(out)
res["current concat kernel"] = timeit(lambda: wp.launch(kern, dim=K.launch_dim(E, KO), inputs=[A(e), A(v), A(v), A(u), A(s), A(s), A(r), A(g), A(out2)], device=wd, stream=stream), dev, 20, 3) * 1e3
print("current correct:", torch.equal(out2, ref))
for k_, val in res.items():
    print(f"{k_:40s} {val:8.1f} us")
