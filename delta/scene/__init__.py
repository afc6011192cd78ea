"""What a capture requires modelled, decided from the capture itself (``results/{dataset}/{subject}/scene.json``)."""
