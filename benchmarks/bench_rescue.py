"""Robot frames whose joint log is far off: fit-pose with and without the
pattern-search rescue, on markers made from the true poses (0.03 px noise).
Usage: python benchmarks/bench_rescue.py MAX_OFFSET_MM MAX_OFFSET_DEG"""
import json, numpy as np, tempfile, time, sys
from pathlib import Path
from conecal.simulate import robot_helix
from conecal.simulate.scenarios import marker_truth
from conecal.scan import load_scan
from conecal.fit.pose import fit_poses, PoseOptions
from conecal.calib.rescue import rescue_frame
from conecal.simulate import write_scan
import yaml, tifffile
# markers level robot scan with the log far off (clusters near 10 mm / 25 deg)
sc = robot_helix(3, n_frames=24, max_offset=(float(sys.argv[1]), float(sys.argv[2])), rows=640, cols=640)
d = Path(tempfile.mkdtemp())/'r'
d.mkdir()
(d/'scan.yaml').write_text(yaml.safe_dump(sc.config))
tifffile.imwrite(d/'projections.tif', np.zeros((sc.n_frames, 640, 640), np.float32), photometric='minisblack')
names=[f"q{j+1}" for j in range(sc.readings.shape[1])]
(d/'log.csv').write_text("frame,time,"+",".join(names)+"\n"+"".join(f"{k},{sc.times[k]},"+",".join(f"{v:.6f}" for v in sc.readings[k])+"\n" for k in range(sc.n_frames)))
ids,cad=sc.phantom
(d/'phantom.csv').write_text("id,x,y,z\n"+"".join(f"{i},{p[0]},{p[1]},{p[2]}\n" for i,p in zip(ids,cad)))
rng=np.random.default_rng(0); T=sc.world.transforms()
frames=[]
truthR=[]
for k in range(sc.n_frames):
    ms=[m for m in marker_truth(sc,k,T[k]) if m['inside']]
    frames.append({"frame":k,"markers":[{"id":None,"x":m['centroid'][0]+rng.normal(0,0.03),"y":m['centroid'][1]+rng.normal(0,0.03),"sigma":0.03,"flags":[]} for m in ms]})
m={"format":"conecal-markers/1","frames":frames}
s=load_scan(d)
for rescue in (False, True):
    t0=time.time()
    poses,_,_=fit_poses(s,m,sc.geometry,PoseOptions(rescue=rescue),rescue=rescue_frame)
    ok=[p for p in poses if p.status=='ok']
    wrong=sum(np.linalg.norm(p.t-T.t[p.frame])>0.5 or np.degrees(np.arccos(np.clip((np.trace(p.R@T.R[p.frame].T)-1)/2,-1,1)))>0.5 for p in ok)
    print('rescue', rescue, f'{len(ok)}/{len(poses)} ok, wrong {wrong}, found by search {sum(p.found_by!="log" for p in ok)}, {time.time()-t0:.1f} s')
    print(sorted({p.status[:60] for p in poses if p.status!='ok'}))
