"""``mdr vocab``: train the ORB bag-of-words vocabulary used for loop closing and relocalization.

Without image folders it rebuilds the packaged vocabulary from the built-in offline sources
(ray-cast textured rooms and matplotlib's sample images); with folders (or bags' left images) it
trains on the user's images, which suits a robot's own environment better.
"""
from __future__ import annotations

import os
import sys
import time

import cv2


def add_parser(subparsers, name, help_text):
    p = subparsers.add_parser(name, help=help_text, description=__doc__)
    p.add_argument("images", nargs="*", help="folders of images (png/jpg/pgm) to train on")
    p.add_argument("-o", "--output", default=None,
                   help="output .npz (default: the packaged src/mdr_slam/data/orb_vocab.npz)")
    p.add_argument("-k", type=int, default=10, help="branching factor (default 10)")
    p.add_argument("-L", type=int, default=4, help="depth: k^L words (default 4)")
    p.add_argument("--max-images", type=int, default=2000)
    p.add_argument("--features", type=int, default=1000, help="ORB features per image")
    p.add_argument("--no-builtin", action="store_true",
                   help="do not add the built-in synthetic/sample images")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run)
    return p


def _folder_images(folders, limit):
    n = 0
    for folder in folders:
        for root, _, files in os.walk(folder):
            for fn in sorted(files):
                if n >= limit:
                    return
                if fn.lower().endswith((".png", ".jpg", ".jpeg", ".pgm", ".bmp")):
                    img = cv2.imread(os.path.join(root, fn), cv2.IMREAD_GRAYSCALE)
                    if img is not None:
                        n += 1
                        yield img


def run(args) -> int:
    # the pose package when the command runs: `mdr --help` imports this module
    from ..pose.vocabulary import (ORBVocabulary, builtin_training_images, default_vocabulary_path,
                                   image_descriptor_sets)
    for f in args.images:
        if not os.path.isdir(f):
            print("mdr vocab: %s is not a folder" % f, file=sys.stderr)
            return 2
    t0 = time.time()
    sets = image_descriptor_sets(_folder_images(args.images, args.max_images), args.features)
    if not args.no_builtin:
        sets += image_descriptor_sets(builtin_training_images(), args.features)
    n_desc = sum(len(s) for s in sets)
    if n_desc < args.k ** 2:
        print("mdr vocab: only %d descriptors from %d images; need more images" % (n_desc, len(sets)),
              file=sys.stderr)
        return 2
    voc = ORBVocabulary.train(sets, k=args.k, L=args.L, seed=args.seed)
    out = args.output or default_vocabulary_path()
    voc.save(out)
    print("mdr vocab: %d images, %d descriptors -> %d words (k=%d, L=%d) in %.1f s: %s (%.0f kB)"
          % (len(sets), n_desc, voc.n_words, args.k, args.L, time.time() - t0, out,
             os.path.getsize(out) / 1024.0))
    return 0
