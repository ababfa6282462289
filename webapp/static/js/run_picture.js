// The Run page's picture card: the held-out picture a frame VQ-VAE run leaves in its run dir
// (the artifact of kind "picture", held_out_frames.png: held-out frames over their reconstructions,
// drawn by the trainer at the end of training, hope_models/train/held_out_picture.py).
//
//   renderPicture(ctx, artifacts, run, current)   artifacts: GET /api/runs/<id>/artifacts' list;
//                                                 current(): false once a newer load has begun
//   clearPicture()                                hides the card (another run is being opened)
//
// DOM contract (tests/test_browser_run.py):
//   #run-picture[hidden]            no picture (a vector run, an unfinished one): nothing is shown,
//                                   never a broken image
//   #run-picture img[data-loaded="1"]   the picture drawn; #run-picture figcaption says what it shows
//
// Like a download, the picture needs the bearer token, which an <img src> cannot send: its bytes are
// fetched with it and shown through a Blob URL, revoked when the next picture replaces it.
import { $ } from "./util.js";

let shownUrl = null;

export function clearPicture() {
  const card = $("#run-picture");
  card.hidden = true;
  const img = $("#run-picture-img");
  img.removeAttribute("src");
  img.dataset.loaded = "0";
  if (shownUrl) URL.revokeObjectURL(shownUrl);
  shownUrl = null;
}

export async function renderPicture(ctx, artifacts, run, current = () => true) {
  const pic = (artifacts || []).find((a) => a.kind === "picture");
  if (!pic) { clearPicture(); return; }
  let blob;
  try {
    const response = await fetch(pic.url, { headers: { Authorization: `Bearer ${ctx.token}` } });
    if (!response.ok) throw new Error(`HTTP ${response.status}`);
    blob = await response.blob();
  } catch (err) {
    console.warn("run picture", err);  // gone since it was listed (a re-run replacing it): nothing to show
    if (current()) clearPicture();
    return;
  }
  if (!current()) return;
  clearPicture();
  shownUrl = URL.createObjectURL(blob);
  const img = $("#run-picture-img");
  img.onload = () => { img.dataset.loaded = "1"; $("#run-picture").hidden = false; };
  img.onerror = () => clearPicture();  // not an image after all: no broken picture
  img.src = shownUrl;
  const step = run && typeof run.step === "number" ? ` (step ${run.step})` : "";
  $("#run-picture-caption").textContent =
    "Top row: frames evenly spaced through the held-out episodes (the validation split, never trained on). " +
    `Bottom row: the VQ-VAE's reconstruction of each, decoded from its codes at the end of training${step}.`;
}
