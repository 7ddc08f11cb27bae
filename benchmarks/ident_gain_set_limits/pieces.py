"""bench_ident_gain_set_limits: affine's delta_lb on one data set with terms of its gain set removed (not proofs)."""
from harness import *
import dataclasses
col = lambda M: np.linalg.norm(M, axis=0)

class V:
    def __init__(s, g, drop=(), M0=None, boxscale=1.0): s.g, s.drop, s.M0, s.bs = g, drop, M0, boxscale
    @property
    def m_lo(s): return s.g.m_lo
    def terms(s, U):
        g = s.g
        ext_F = np.sqrt(np.maximum(np.linalg.eigvalsh(I._gram_rows(np.einsum("lik,lp->pik", g.DF, U)))[:, -1], 0.0))
        quad = np.abs(np.linalg.eigvalsh(np.einsum("lij,lp->pij", g.quad, U))).max(axis=1)
        h_A = col(g.half_A @ U) * np.sqrt(s.bs)
        T = {"W1": col(g.WX.T @ U) + col(g.WU.T @ U), "ball": g.ball * col(U),
             "eB": np.minimum(-s.bs * g.centre @ U + g.half_B * np.sqrt(s.bs) * h_A, g.b * g.t_e * s.bs * col(g.acl0 @ U)),
             "quad": quad, "cubic": g.ext_B * g.ext_E * ext_F,
             "e2": s.bs * (g.ext_B * (col(g.CA @ U) + g.half * h_A) + (g.e_B + g.ext_B * g.t_e) * ext_F),
             "box": g.box @ np.abs(U) if g.box is not None else 0 * col(U)}
        return T
    def support(s, U):
        T = s.terms(U)
        g = sum(v for k, v in T.items() if k not in s.drop)
        if s.M0: return g / s.M0
        return np.maximum(g / s.g.m_lo, g / s.g.m_hi)

def M0of(a, c): return (c.theta0[:, 4:].T @ c.P0 @ c.theta0[:, 4:]).item() + a.lqr_weights[1]
if __name__ == "__main__":
    task, atk = data(int(sys.argv[1]) if len(sys.argv) > 1 else 0)
    vs = [("base", {}), ("M0", {"M0": True}), ("no e2", {"drop": ("e2",)}), ("no eB", {"drop": ("eB",)}),
          ("box/2", {"boxscale": 0.5}), ("no quad,cubic", {"drop": ("quad", "cubic")}), ("no box(fit2)", {"drop": ("box",)}),
          ("M0 + no e2 + no quad", {"M0": True, "drop": ("e2", "quad", "cubic")})]
    for name, kw in vs:
        t = time.process_time()
        def var(a, c, g, kw=kw):
            kw = dict(kw)
            if kw.get("M0"): kw["M0"] = M0of(a, c)
            return V(g, **kw)
        print(name, round(bisect(atk, 0.005, 0.016, var), 6), "cpu %.1f load %.1f" % (time.process_time() - t, os.getloadavg()[0]), flush=True)
