"""bench_ident_gain_set_limits: M = R + B'PB's certified range at one budget, its terms, and M over sphere poisonings."""
from harness import *
task, atk = data(0)
import bilevel.robust.identification as I
orig = I.AffineGainSet
delta = float(sys.argv[1]) if len(sys.argv) > 1 else 0.0068
# recompute M pieces as affine_gain_set does
A, B = atk.setting.state_space
Y0, Z0 = atk.regression(atk.signals); c = I.clean(atk, least_squares_fit(Y0, Z0))
maps = I.model_maps(atk); E1, Wmap = I.riccati_maps(c)
in_model, in_gain = I.second_parts(atk, c, Wmap, delta)
shape = I.model_shape(atk, delta, maps, ball=True, second=in_model)
sol = I.affine_sandwich(atk, c, shape, E1, Wmap)
g = I.affine_gain_set(atk, c, delta, shape, sol, maps, E1, Wmap, in_gain)
n, nm = c.theta0.shape; B0 = c.theta0[:, n:]
Ds = [shape.D[:, j * nm:(j + 1) * nm] for j in range(shape.k)]
E_all = np.array([E.ravel() for E in E1]).T
Ej = [I._sym((E_all @ D.ravel()).reshape(n, n)) for D in Ds]
dB = [D[:, n:] for D in Ds]
M0 = atk.lqr_weights[1] + (B0.T @ c.P0 @ B0).item()
lin = np.array([(2 * B0.T @ c.P0 @ b + B0.T @ E @ B0).item() for b, E in zip(dB, Ej)])
Mq = np.array([[(dB[i].T @ c.P0 @ dB[j] + dB[i].T @ Ej[j] @ B0 + dB[j].T @ Ej[i] @ B0).item() for j in range(shape.k)] for i in range(shape.k)])
Xc, Yc = I._sym(sol["Xc"]), I._sym(sol["Yc"]); H, C = 0.5 * I._sym(Xc - Yc), 0.5 * I._sym(Xc + Yc) - c.P0
print("M0", M0, "m_lo", g.m_lo, "m_hi", g.m_hi)
print("lin", np.linalg.norm(lin), "Mq", np.abs(np.linalg.eigvalsh(I._sym(Mq))).max(), "cubic", g.ext_B**2*g.ext_E, "2extB eB", 2*g.ext_B*g.e_B, "extB^2 te", g.ext_B**2*g.t_e, "centre_M", (B0.T@C@B0).item(), "half_B^2", g.half_B**2)
# exact lin over the poisoning balls
r_X, r_U = delta*np.linalg.norm(atk.signals["X"]), delta*np.linalg.norm(atk.signals["U"])
Mmap = np.array([(2 * B0.T @ c.P0 @ U[:, n:] + B0.T @ I._sym((E_all @ U.ravel()).reshape(n, n)) @ B0).item() for U in np.eye(c.theta0.size).reshape(-1, n, nm)])
print("lin exact on the balls", r_X*np.linalg.norm(Mmap@maps[0]) + r_U*np.linalg.norm(Mmap@maps[1]))
# sample true M over refits
rng = np.random.default_rng(0)
from bilevel.robust.soundness import sphere_poisoning
from bilevel.robust import as_target
from bilevel.ddc.model_based import lqr_gain
tg = as_target(atk)
Ms = []
for _ in range(300):
    th = tg.refit(tg.poisoned(sphere_poisoning(tg, delta, rng)))
    K, P = lqr_gain(th[:, :n], th[:, n:], atk.lqr_weights[0]*np.eye(n), atk.lqr_weights[1]*np.eye(1))
    Ms.append(atk.lqr_weights[1] + (th[:, n:].T @ P @ th[:, n:]).item())
print("sampled M range", min(Ms), max(Ms))
