"""`treetraits eval`: the paper's Table I reproduced on the digital twin.

cases.py holds the cases and the paper's published numbers, metrics.py the pure scoring
(matching detections to truth, MAPE per row, RMSE), run.py the simulate-and-replay
orchestration with its cache, table.py and plot.py the outputs.
"""
