"""One VRFT certificate at N = 512, delta 0.003, on the reproduction's first three data sets: cold (operators built),
warm (kept), and warm without the joint bound (options={"joint": False}); CPU (process_time) and wall seconds, load."""
import time, numpy as np, os
import bilevel as bl
from bilevel.problems.vrft_instance import attack_instance
from bilevel.experiments.certify import certify_tasks
tasks=[t for t in certify_tasks(32, False, 0, 10000, ("vrft",)) if t["size"]==512][:3]
for t in tasks:
    atk=attack_instance("destabilize","B",0.0,0.0,seed=t["seed"],N=512)
    for label in ("cold","warm"):
        l0=os.getloadavg()[0]; c=time.process_time(); w=time.perf_counter()
        cert=bl.certify(atk,0.003)
        print(t["seed"], label, cert.proof.value, "cpu %.2f wall %.2f load %.1f"%(time.process_time()-c, time.perf_counter()-w, l0), flush=True)
    for joint in (False,):
        c=time.process_time(); w=time.perf_counter(); cert=bl.certify(atk,0.003,options={"joint":False})
        print(t["seed"], "warm, joint off", cert.proof.value, "cpu %.2f wall %.2f"%(time.process_time()-c, time.perf_counter()-w), flush=True)
