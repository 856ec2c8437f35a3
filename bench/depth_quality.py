"""Sky and edge scores of exported curated depth against the synthetic ground truth, until
`dist4d eval` reports them (issue 14). Per camera: sky IoU (prediction >= 99 m vs ground-truth
sky, pooled over the camera's images), share of ground-truth sky given a structure depth (< 80 m,
pooled), bad pixels (relative error > 10% / > 25% over ground truth 0.1-80 m, mean of images),
unclamped Abs Rel, and depth-boundary accuracy / completeness in px (OpenCV Canny 30/80 on log
depth scaled to 0-255 over 0.1-100 m, sky at 100 m, distances capped at 10 px; iBims-1 style).

    .venv-peers/bin/python bench/depth_quality.py SYNTH_DATASET OUT_DIR
"""
import os, sys, glob, numpy as np
os.environ["OPENCV_IO_ENABLE_OPENEXR"]="1"
import cv2
from scipy import ndimage
data, out = sys.argv[1], sys.argv[2]
CAMS=["CAM_FRONT","CAM_FRONT_RIGHT","CAM_BACK_RIGHT","CAM_BACK","CAM_BACK_LEFT","CAM_FRONT_LEFT"]
def edges(d):
    l=np.log(np.clip(d,0.1,100)).astype(np.float32)
    l=(l-np.log(0.1))/(np.log(100)-np.log(0.1))*255
    return cv2.Canny(l.astype(np.uint8),30,80)>0  # rough
tot=[]; I={}; U={}; S={}; G={}
for cam in CAMS:
    gts=sorted(glob.glob(f"{data}/groundtruth/depth/{cam}/*.exr"))
    rows=[]
    for k,g in enumerate(gts):
        p=f"{out}/synth-0000/{cam}/{k:03d}_depth.npy"
        if not os.path.exists(p): continue
        pred=np.load(p); gt=cv2.imread(g,cv2.IMREAD_UNCHANGED)
        gsky=~np.isfinite(gt); psky=pred>=99
        u=(gsky|psky).sum(); iou=(gsky&psky).sum()/u if u else 1.0
        s2s=(gsky&(pred<80)).sum()/max(gsky.sum(),1)
        v=np.isfinite(gt)&(gt>0.1)&(gt<80)
        rel=np.abs(pred[v]-gt[v])/gt[v]
        b10=(rel>0.1).mean(); b25=(rel>0.25).mean(); ar=rel.mean()
        g2=np.where(gsky,100,gt); p2=np.where(pred>0,pred,100)
        eg, ep = edges(g2), edges(p2)
        dg=np.minimum(ndimage.distance_transform_edt(~eg),10); dp=np.minimum(ndimage.distance_transform_edt(~ep),10)
        acc=dg[ep].mean() if ep.any() else 0; comp=dp[eg].mean() if eg.any() else 0
        rows.append([iou,s2s,b10,b25,ar,acc,comp]); I[cam]=I.get(cam,0)+(gsky&psky).sum(); S[cam]=S.get(cam,0)+(gsky&(pred<80)).sum(); G[cam]=G.get(cam,0)+gsky.sum(); U[cam]=U.get(cam,0)+(gsky|psky).sum(); None
    r=np.mean(rows,0); r[0]=I[cam]/max(U[cam],1); r[1]=S[cam]/max(G[cam],1); tot.append(r)
    print(f"{cam:16s} skyIoU {r[0]:.3f} sky<80 {r[1]:.3f} bad10 {r[2]*100:.2f}% bad25 {r[3]*100:.2f}% absrel {r[4]:.4f} bacc {r[5]:.2f} bcomp {r[6]:.2f}")
r=np.mean(tot,0)
print(f"{'mean':16s} skyIoU {r[0]:.3f} sky<80 {r[1]:.3f} bad10 {r[2]*100:.2f}% bad25 {r[3]*100:.2f}% absrel {r[4]:.4f} bacc {r[5]:.2f} bcomp {r[6]:.2f}")
