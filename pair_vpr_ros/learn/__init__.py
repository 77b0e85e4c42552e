"""Training and evaluation: datasets on disk (ROS-free, nothing is downloaded), Recall@N, training.

Place collections (training; ``load_places("KIND:ROOT")``):

- ``gsv``: GSV-Cities. ``ROOT/Dataframes/<City>.csv`` (columns place_id, year, month, northdeg,
  city_id, lat, lon, panoid) and ``ROOT/Images/<city_id>/<name>.jpg`` where, as in the dataset's
  reference loader, ``name = f"{city_id}_{place_id:07d}_{year:04d}_{month:02d}_{northdeg:03d}_"
  f"{lat}_{lon}_{panoid}"`` with lat/lon written as Python ``str(float)``. ``Images/<City>/`` (the
  CSV stem) is accepted too. Places with fewer than 4 images are dropped; rows without an image
  file are counted in ``skipped_images``.
- ``folders``: ``ROOT/<place>/*.{png,jpg,...}`` (``images.encoded.IMAGE_SUFFIXES``), one
  subfolder per place, >= 2 images each.
- ``gldv2``: Google Landmarks v2. ``ROOT/train_clean.csv`` (landmark_id, images: space-separated
  ids) if present, else ``ROOT/train.csv`` (id, url, landmark_id); image ``id`` lives at
  ``ROOT/train/<id[0]>/<id[1]>/<id[2]>/<id>.jpg``. One landmark is one place.
- ``sfxl``: SF-XL. Images anywhere under ROOT named ``@east@north@zone@letter@lat@lon@pano@tile@
  heading@...``; a place is a square UTM cell (default 10 m) times a heading sector (default 30
  degrees), like CosPlace's cells but without its group separation.

Evaluation sets (``load_eval_set(ROOT)``): ``ROOT/database/`` and ``ROOT/queries/`` image folders
(searched recursively, sorted by relative path). Ground truth is ``ROOT/ground_truth.npy`` when
present, otherwise UTM coordinates in the file names (``@easting@northing@...``) with positives
within 25 m. The .npy is read without pickle (a pickle can run code): an integer array
``[Q, K]`` of positive database indices per query padded with -1, or a boolean ``[Q, DB]``
matrix. The ragged object arrays other VPR code writes are refused with the one-line conversion
(``GT_CONVERT``) to run once on a file you trust.
Modules: ``places`` (training collections), ``eval_sets`` (evaluation sets and ground truth),
``image_files`` (listing and reading image files), ``recall`` (Recall@N of one set, re-ranked as
the node does), ``evaluate`` (``pairvpr-eval``), ``heldout``, ``train/`` (both training stages).
"""
