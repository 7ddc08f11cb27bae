"""bench_ident_gain_set_limits: -W/M bounded as a linear-fractional function of the poisoning (sound), against the built set."""
from harness import *
col = lambda M: np.linalg.norm(M, axis=0)

class LF:
    """linear-fractional support: u'd = -Wu/M."""
    def __init__(s, g, pX, pU, qX, qU, e):
        s.g, s.m_lo = g, e - np.linalg.norm(qX) - np.linalg.norm(qU)
        s.pX, s.pU, s.qX, s.qU, s.e = pX, pU, qX, qU, e
    def support(s, U):
        g = s.g
        old = g.support(U)
        a, b = g.WX.T @ U, g.WU.T @ U      # numerator linear part -u'W1 = -(a'z)... sup symmetric
        cc = old * 0  # rest: g minus the W1 image
        gg = np.where(old > 0, old * g.m_lo, old * g.m_hi)  # recover g
        rest = gg - col(a) - col(b)
        # |p - t q|: p = -a (n_X, cols), q fixed vector
        aa, bb = np.sum(a * a, 0), np.sum(b * b, 0)
        aq, bq = -(s.qX @ a), -(s.qU @ b)
        qq, rr = s.qX @ s.qX, s.qU @ s.qU
        phi = lambda t: np.sqrt(np.maximum(aa - 2 * t * aq + t * t * qq, 0)) + np.sqrt(np.maximum(bb - 2 * t * bq + t * t * rr, 0)) + rest - t * s.e
        lo, hi = np.zeros_like(old), np.maximum(old, 0) * 2 + 1e-9
        # ensure hi feasible
        for _ in range(60):
            bad = phi(hi) > 0
            if not bad.any(): break
            hi = np.where(bad, hi * 2, hi)
        for _ in range(50):
            mid = 0.5 * (lo + hi); ok = phi(mid) <= 0
            hi, lo = np.where(ok, mid, hi), np.where(ok, lo, mid)
        new = np.where(phi(np.zeros_like(old)) <= 0, 0.0, hi)
        return np.minimum(old, new)

def lf_variant(atk, c, g, delta):
    n, nm = c.theta0.shape; B0 = c.theta0[:, n:]
    maps = I.model_maps(atk); E1, Wmap = I.riccati_maps(c)
    E_all = np.array([E.ravel() for E in E1]).T
    Mmap = np.array([(2 * B0.T @ c.P0 @ U[:, n:] + B0.T @ I._sym((E_all @ U.ravel()).reshape(n, n)) @ B0).item() for U in np.eye(c.theta0.size).reshape(-1, n, nm)])
    r_X, r_U = delta*np.linalg.norm(atk.signals["X"]), delta*np.linalg.norm(atk.signals["U"])
    so = I.second_order(atk); cubic = so.cubic(delta)
    Mbox = so.bound(Mmap[None, :])[0] * delta**2 + np.linalg.norm(Mmap) * cubic
    M0 = atk.lqr_weights[1] + (B0.T @ c.P0 @ B0).item()
    # second-order rest of M as in affine_gain_set: spread - ||lin||; reconstruct: m_lo = M0 + centre - half_B^2 - spread
    return Mmap, Mbox, M0, r_X, r_U, maps

if __name__ == "__main__":
    import bilevel.robust.identification as I2
    i = int(sys.argv[1]) if len(sys.argv) > 1 else 0
    task, atk = data(i)
    # need lin norm used in spread: recompute like mspread
    def var(a, c, g):
        Mmap, Mbox, M0, r_X, r_U, maps = lf_variant(a, c, g, var.delta)
        n, nm = c.theta0.shape
        qX, qU = Mmap @ maps[0] * r_X, Mmap @ maps[1] * r_U
        # spread = lin_norm + rest2 ; m_lo = M0 + centre - half^2 - spread -> e = m_lo + lin_norm - Mbox
        lin_norm = var.lin_norm(a, c, g)
        e = g.m_lo + lin_norm - Mbox
        return LF(g, None, None, qX, qU, e)
    def lin_norm(a, c, g):
        return var.cache
    orig = I.affine_gain_set
    def patched(atk_, c, delta, shape, sol, maps, E1, Wmap, second=None):
        n, nm = c.theta0.shape; B0 = c.theta0[:, n:]
        Ds = [shape.D[:, j * nm:(j + 1) * nm] for j in range(shape.k)]
        E_all = np.array([E.ravel() for E in E1]).T
        lin = np.array([(2 * B0.T @ c.P0 @ D[:, n:] + B0.T @ I._sym((E_all @ D.ravel()).reshape(n, n)) @ B0).item() for D in Ds])
        var.cache = np.linalg.norm(lin); var.delta = delta
        return orig(atk_, c, delta, shape, sol, maps, E1, Wmap, second)
    I.affine_gain_set = patched
    var.lin_norm = lin_norm
    for name, v in [("base(fixed sweep)", None), ("linear-fractional", var)]:
        t = time.process_time()
        print(i, name, round(bisect(atk, 0.005, 0.016, v), 6), "cpu %.1f load %.1f" % (time.process_time() - t, os.getloadavg()[0]), flush=True)
