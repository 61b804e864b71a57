"""zenrl.learner"""
