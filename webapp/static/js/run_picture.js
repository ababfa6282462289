// The Run page's picture card: the held-out picture a frame run leaves in its run dir (the artifact
// of kind "picture", drawn by the trainer at the end of training, hope_models/train/held_out_picture.py):
// a frame VQ-VAE's held_out_frames.png (held-out frames over their reconstructions) or a grid Mid
// Loop's predicted_frames.png (a held-out window a row: the frame now, then at each horizon the
// predicted frame beside the recorded one). The heading, alt text and caption say which.
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
  const words = WORDS[pic.name] || WORDS["held_out_frames.png"];
  $("#run-picture h2").textContent = words.title;
  img.alt = words.alt;
  $("#run-picture-caption").textContent = words.caption(step);
}

// what each picture shows, by its file name (hope_models/train/held_out_picture.py)
const WORDS = {
  "held_out_frames.png": {
    title: "Held-out frames",
    alt: "held-out frames (top row) over the VQ-VAE's reconstructions (bottom row)",
    caption: (step) =>
      "Top row: frames evenly spaced through the held-out episodes (the validation split, never trained on). " +
      `Bottom row: the VQ-VAE's reconstruction of each, decoded from its codes at the end of training${step}.`,
  },
  "predicted_frames.png": {
    title: "Predicted frames",
    alt: "held-out windows, one a row: the frame now, then predicted and recorded frames at each horizon",
    caption: (step) =>
      "Each row is a window of the held-out episodes (the validation split, never trained on). Columns, left " +
      "to right: the frame now; predicted +0.5 s; recorded +0.5 s; predicted +1 s; recorded +1 s (the run's " +
      "horizons, 0.5 s and 1 s by default). Predicted: the frozen VQ-VAE's decoding of the Mid Loop's most " +
      "probable code for each cell (mixed with copy-last, as its accuracy counts); recorded: the camera's " +
      `frame at that time, from the dataset, not decoded. Drawn at the end of training${step}.`,
  },
};
